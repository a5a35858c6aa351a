"""Products derived from detections and maps (forestry metrics from clouds:
:mod:`stemmap.products.forestry`)."""
