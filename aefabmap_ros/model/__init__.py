"""The model directory the nodes load (vocabulary + Chow-Liu tree + feature settings) and the training
that writes it."""

__all__ = ["directory", "training"]
