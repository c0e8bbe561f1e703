"""Visual vocabularies: the ``Quantizer`` protocol and ``train_vocabulary`` (``base``), the registry of
kinds (``kinds``), k-means, PCA, the autoencoder and
the encoder distilled from it (``distilled``). A new vocabulary kind is a module here plus a
line in ``kinds``."""

__all__ = ["autoencoder", "base", "distilled", "kinds", "kmeans", "pca"]
