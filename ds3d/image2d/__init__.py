"""The 2D stage, inference: image -> 2D pose, unaries and left/right decision.

params.py       what training fixed (ModelParams) and what inference may change
result.py       Estimate2D, the stage's batched result
crops.py        the working region and base scale of each image (or person box)
features.py     per-pixel channels and the forests' pixel comparisons
forest.py       random forests as tensors, tensorised traversal
cascade.py      the forest cascade over a batch (auto-context layers)
jointnet.py     the joint network, a second unary
psm.py          pictorial structure model; maxconv.py its max-convolution
left_right.py   which labelling of left and right fits; facing.py the facing CNN
model_files.py  a trained model on disk and its manifest
estimator.py    PoseEstimator2D: the pyramid, the choice of scale, all of the above wired
"""
