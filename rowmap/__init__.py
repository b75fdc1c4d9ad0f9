"""The row-mapping library the stages and the benchmarks share, between the model (nerf/) and the DAG
(stages/): a window's data for a fit (window_data), the render contract of nerf_fit (renders), fruit
geometry across windows (geometry), the detector's fruit segments of a frame (detections), panoptic
scoring (scoring) and instance colours (colours). Stages call it; no stage imports another stage.
"""
