"""FAB-MAP: Chow-Liu tree, the FAB-MAP 2 / FAB-MAP 1 engines and posterior, the online place recognizer
with its map file, and temporal consistency."""

__all__ = ["chowliu", "consistency", "engines", "recognizer"]
