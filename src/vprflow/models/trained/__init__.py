"""Trained VPR models in plain torch, with checkpoint loaders: NetVLAD, SALAD, BoQ-DINOv2,
MegaLoc (ViT / VGG16 based) and CosPlace, EigenPlaces, MixVPR, Conv-AP, BoQ-ResNet50
(ResNet based, :mod:`vprflow.models.trunks.resnet`)."""
