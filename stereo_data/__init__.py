"""Stereo data: file formats (``formats``), dataset readers (``readers``) and procedural scenes
with exact ground truth (``synthetic``). Imports nothing from the rest of the project."""
