"""Rendering: ray casting (open3d) and rasterizing."""
