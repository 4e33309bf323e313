"""One multiplane image: its fields, the compiled plane sampler, ray and image rendering."""
