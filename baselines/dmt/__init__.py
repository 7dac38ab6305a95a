"""DMT (Arikan et al. 2014): per-depth-map graph-cut labeling and runtime triangulation + stitching."""

from baselines.dmt.labeling import DMTLabelingConfig, dmt_labels, read_cache
from baselines.dmt.renderer import STAGES, DMTConfig, DMTRenderer

__all__ = ["DMTConfig", "DMTRenderer", "DMTLabelingConfig", "dmt_labels", "read_cache", "STAGES"]
