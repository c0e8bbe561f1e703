"""Local features: the registry of feature types (``kinds``), the descriptor-kind policy (``descriptors``),
extraction and the one descriptor matcher (``matching``). A new feature type goes here."""

__all__ = ["descriptors", "extraction", "kinds", "matching"]
