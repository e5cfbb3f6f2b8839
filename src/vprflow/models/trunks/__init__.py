"""Convolutional trunks in plain torch, in torchvision's state-dict layouts."""
