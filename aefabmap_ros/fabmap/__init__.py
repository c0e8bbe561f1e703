"""FAB-MAP: settings, Chow-Liu tree, the FAB-MAP 2 / FAB-MAP 1 engines, the posterior, the online place recognizer
and its map file, temporal consistency, and openFABMAP's files (interchange with openFABMAPcli)."""

__all__ = [
    "chowliu",
    "config",
    "consistency",
    "engines",
    "index",
    "kernels",
    "map_file",
    "map_tools",
    "observation",
    "openfabmap",
    "place_table",
    "posterior",
    "recognition",
    "recognizer",
    "robot_track",
    "sessions",
]
