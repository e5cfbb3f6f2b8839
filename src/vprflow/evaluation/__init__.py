"""What the retrievals are worth: Recall@N (``recall``), precision-recall
(``precision_recall``), training-free re-ranking (``rerank``) and the figures of results
(``figures``).
"""
