"""An example railtraj plugin package (see voxel_corner.py)."""
