"""Visual vocabularies: the ``Quantizer`` protocol and ``train_vocabulary`` (``base``), the registry of
kinds (``kinds``), k-means, PCA and the autoencoder. A new vocabulary kind is a module here plus a
line in ``kinds``."""

__all__ = ["autoencoder", "base", "kinds", "kmeans", "pca"]
