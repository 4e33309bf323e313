"""Scenes (folders, LLFF, the synthetic layered scenes) and photo intake."""
