"""The synthetic town: a textured 3-D world rendered along looping routes, with poses and ground truth.
``town.generate_sequence`` puts together the parameters (``config``), the world and its texture atlas
(``world``, ``textures``, ``ground_and_sky``), the drive (``trajectory``) and the renderer (``renderer``)."""

__all__ = ["config", "ground_and_sky", "renderer", "textures", "town", "trajectory", "world"]
