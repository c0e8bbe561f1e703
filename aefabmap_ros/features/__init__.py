"""Local features: the registry of feature types (``kinds``), the descriptor-kind policy (``descriptors``),
extraction and image decoding. A new feature type goes here."""

__all__ = ["descriptors", "extraction", "images", "kinds"]
