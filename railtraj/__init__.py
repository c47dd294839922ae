"""railtraj: trajectory correction for rail mobile mapping in tunnels.

Finds the same geometric features in several runs' point clouds, matches them, optimizes the
runs' trajectories so they agree, re-georeferences the clouds and exports anchor observations
for GNSS/INS post-processing.
"""

__version__ = "0.1.0"
