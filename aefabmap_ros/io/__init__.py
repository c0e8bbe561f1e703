"""Files, bags and messages: rosbag2 bags, image sources, ROS image encodings and image messages, the
check of stamps, poses and covariances read from messages, RGB-D recordings, config files, atomic writes,
versioned .npz files, append-only chunk folders, digests. A new file format goes here."""

__all__ = ["atomic", "bag_messages", "bags", "chunk_folder", "config_files", "digests", "image_encodings",
           "image_messages", "message_values", "npz_files", "rgbd", "sources"]
