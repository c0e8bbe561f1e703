import numpy as np

from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.visualization.closure_album import AlbumConfig, ClosureAlbum
from aefabmap_ros.visualization.match_picture import decode_jpeg


def _features(seed: int) -> Features:
    rng = np.random.default_rng(seed)
    keypoints = np.zeros((40, 5), np.float32)
    keypoints[:, :2] = rng.uniform(0, 300, size=(40, 2))
    return Features(keypoints, rng.integers(0, 255, size=(40, 128)).astype(np.float32), "sift")


def test_only_frames_with_features_get_a_thumbnail_whichever_arrives_first():
    album = ClosureAlbum(AlbumConfig(thumbnail_width=160), VerificationConfig())
    image = np.full((240, 320), 128, np.uint8)
    album.add_image(1, image)  # image first
    album.add_features(1, _features(1))
    album.add_features(2, _features(2))  # features first
    album.add_image(2, image)
    album.add_image(3, image)  # a frame the detector skipped: never gets features
    assert 1 in album.thumbnails and 2 in album.thumbnails and 3 not in album.thumbnails
    assert 3 in album.waiting_images


def test_picture_needs_both_frames_and_is_a_side_by_side_jpeg():
    album = ClosureAlbum(AlbumConfig(thumbnail_width=160), VerificationConfig())
    for stamp in (1, 2):
        album.add_features(stamp, _features(stamp))
        album.add_image(stamp, np.full((240, 320), 100, np.uint8))
    assert album.picture(1, 3, "q", refused=False) is None
    picture = album.picture(1, 2, "q", refused=True)
    assert picture is not None
    decoded = decode_jpeg(picture.jpeg)
    assert decoded.shape[1] == 2 * 160 and decoded.shape[0] > 120  # two thumbnails under a banner
    assert 0 <= picture.inliers <= picture.matches
