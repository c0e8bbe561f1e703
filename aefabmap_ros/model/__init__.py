"""The model directory the nodes load (vocabulary + Chow-Liu tree + feature settings): its layout, saving and
full loading (``directory``), its files read without a vocabulary (``files``), the part each node loads
(``parts``), the conversion of folders whose network is still in torch's format (``convert``), and the
training that writes it (``training``)."""

__all__ = ["convert", "directory", "files", "parts", "training"]
