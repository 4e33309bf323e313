"""Baked scenes and what serves them: the compiled renderer, glTF export, videos."""
