"""3DGS RGB-D SLAM (SplaTAM-style tracking and mapping) with PWAS importance."""
