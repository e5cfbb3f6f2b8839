"""What the trained models share, in plain torch: the convolutional trunks in
torchvision's state-dict layouts, VGG16 (:mod:`.vgg`) and ResNet-18/34/50/101/152
(:mod:`.resnet`); DINOv2 ViT-B/14 as the ViT models call it (:mod:`.dinov2`); and
reading a published state dict into a model (:mod:`.state_dicts`)."""
