"""What grows models: the 2D stage's forest cascade, PSM and networks (`ds3d train-2d`). Never
imported by inference code; the models it writes are read by ds3d.image2d.model_files.

    config.py    TrainConfig: what to train, the defaults are the full model
    quantize.py  the int8 copy of the joint network for the people search
    images.py    the training images at the working scale (LSP + LSPet), labels
    forests.py   the cascade's layers, grown by scikit-learn on sampled pixels
    psm.py       the PSM's pairwise mixtures from the training poses
    jointnet.py  the joint network (a second unary)
    facing.py    the facing CNN (for models without a joint network)
    image2d.py   train(): all of it, written as one model directory
"""
