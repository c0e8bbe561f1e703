"""Visual vocabularies: the ``Quantizer`` protocol and ``train_vocabulary`` (``base``), the settings of
each kind (``config``), the registry of kinds (``kinds``), k-means, PCA, the autoencoder (``autoencoder``,
trained by ``autoencoder_training`` with ``training_checkpoint``) and the encoder distilled from it
(``distilled``). A new vocabulary kind is a module here plus a line in ``kinds``."""

__all__ = ["autoencoder", "autoencoder_training", "base", "config", "distilled", "kinds", "kmeans", "pca",
           "training_checkpoint"]
