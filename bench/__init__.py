"""The lab's bench: the measured speed-for-accuracy trade of bundles (`vs2t-edge bench`).

A tool for the people who choose a bundle, not part of the cell: it needs onnx and matplotlib
(`pip install .[bench]`), which the lean runtime does not carry. It measures the cell's own code
(vs2t_edge.runtime) and imports nothing of train or export.
"""
