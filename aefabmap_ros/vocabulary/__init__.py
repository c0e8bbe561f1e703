"""Visual vocabularies: the ``Quantizer`` protocol and ``train_vocabulary`` (``base``), the settings of
each kind (``config``) and the registry of kinds (``kinds``).

What the nodes run, numpy only: the k-means quantizer (``kmeans``), the autoencoder quantizer
(``autoencoder``) with its encoders, the MLP (``mlp_encoder``) and the paper's convolutional network
(``conv_encoder``), the nearest-centre search (``nearest``), PCA (``pca``), and the reader of network
weights still in torch's format (``legacy_weights``, torch imported only for such a folder).
What trains them, with torch, faiss and scikit-learn: ``kmeans_training``, ``autoencoder_training`` with
the torch networks (``autoencoder_network``), the distillation (``distilled``) and the resumable state
(``training_checkpoint``). A new vocabulary kind is a runtime and a training module plus a line in ``kinds``."""

__all__ = ["autoencoder", "autoencoder_network", "autoencoder_training", "base", "config", "conv_encoder", "distilled",
           "kinds", "kmeans", "kmeans_training", "legacy_weights", "mlp_encoder", "nearest", "pca",
           "training_checkpoint"]
