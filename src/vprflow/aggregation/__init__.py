"""From patch features to descriptors: VLAD and its vocabularies (``vlad``,
``vocabularies``), SegVLAD (``segvlad``), SNSM (``snsm``), the pooling baselines
(``pooling``) and PCA (``pca``). Plain functions over arrays.
"""
