"""Files, bags and messages: rosbag2 bags, image sources, ROS image encodings and image messages, RGB-D
recordings, config files, atomic writes, versioned .npz files, append-only chunk folders,
digests. A new file format goes here."""

__all__ = ["atomic", "bags", "chunk_folder", "config_files", "digests", "image_encodings", "image_messages",
           "npz_files", "rgbd", "sources"]
