"""Visual vocabularies: the ``Quantizer`` protocol and ``train_vocabulary`` (``base``), the settings of
each kind (``config``), the registry of kinds (``kinds``), k-means, PCA, the autoencoders (``autoencoder``,
trained by ``autoencoder_training`` with ``training_checkpoint``), the numpy MLP encoder that quantizes
(``mlp_encoder``) and the distillation of the paper's network into one (``distilled``). A new vocabulary
kind is a module here plus a line in ``kinds``."""

__all__ = ["autoencoder", "autoencoder_training", "base", "config", "distilled", "kinds", "kmeans", "mlp_encoder",
           "pca", "training_checkpoint"]
