"""Convolutional trunks in plain torch, in torchvision's state-dict layouts: VGG16
(:mod:`.vgg`) and ResNet-18/34/50/101/152 (:mod:`.resnet`)."""
