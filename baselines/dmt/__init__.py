"""DMT (Arikan et al., TVCG 2014): per-depth-map labeling, runtime triangulation + stitching."""
