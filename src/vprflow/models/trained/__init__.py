"""Trained VPR models (NetVLAD, SALAD, BoQ, MegaLoc) in plain torch, with checkpoint loaders."""
