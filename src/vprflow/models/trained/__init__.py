"""Trained VPR models in plain torch, with checkpoint loaders: NetVLAD, SALAD, BoQ-DINOv2,
VLAD-BuFF, MegaLoc (VGG16 / DINOv2 based) and CosPlace, EigenPlaces, MixVPR, Conv-AP,
BoQ-ResNet50 (ResNet based); the parts they share are in :mod:`vprflow.models.trunks`,
their published files and input sizes in :mod:`vprflow.models.kinds`."""
