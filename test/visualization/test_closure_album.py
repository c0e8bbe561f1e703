import numpy as np
import pytest

from aefabmap_ros.errors import DataError
from aefabmap_ros.features.extraction import Features
from aefabmap_ros.verification.geometric import VerificationConfig
from aefabmap_ros.visualization.closure_album import AlbumConfig, ClosureAlbum, ViewFrame
from aefabmap_ros.visualization.match_picture import decode_jpeg, encode_jpeg, make_thumbnail

IMAGE_WIDTH = 320


def _features(seed: int) -> Features:
    rng = np.random.default_rng(seed)
    keypoints = np.zeros((40, 5), np.float32)
    keypoints[:, :2] = rng.uniform(0, 300, size=(40, 2))
    return Features(keypoints, rng.integers(0, 255, size=(40, 128)).astype(np.float32), "sift")


class FakeWire:
    """Stands in for serialization: a frame's bytes name it; the loader gives back what was stored under it."""

    def __init__(self) -> None:
        self.frames: dict[bytes, ViewFrame] = {}
        self.loaded: list[bytes] = []

    def serialize(self, name: str, frame: ViewFrame, size: int = 100) -> bytes:
        blob = name.encode().ljust(size, b"\0")
        self.frames[blob] = frame
        return blob

    def load(self, blob: bytes) -> ViewFrame:
        self.loaded.append(blob)
        if blob not in self.frames:
            raise DataError("not a frame")
        return self.frames[blob]


def _frame(seed: int) -> ViewFrame:
    thumbnail = make_thumbnail(np.full((240, IMAGE_WIDTH), 100, np.uint8), 160)
    return ViewFrame(_features(seed), IMAGE_WIDTH, thumbnail)


def test_frames_are_decoded_only_for_a_picture_and_it_is_a_side_by_side_jpeg():
    wire = FakeWire()
    album = ClosureAlbum(AlbumConfig(), VerificationConfig(), wire.load)
    for stamp in (1, 2, 3):
        album.add_frame(stamp, wire.serialize(str(stamp), _frame(stamp)))
    assert wire.loaded == []  # keeping frames decodes nothing
    assert album.picture(1, 4, "q", refused=False) is None  # frame 4 never came
    picture = album.picture(1, 2, "q", refused=True)
    assert picture is not None and len(wire.loaded) == 2
    decoded = decode_jpeg(picture.jpeg)
    assert decoded.shape[1] == 2 * 160 and decoded.shape[0] > 120  # two thumbnails under a banner
    assert 0 <= picture.inliers <= picture.matches


def test_the_album_is_bounded_by_bytes_oldest_frames_first():
    wire = FakeWire()
    album = ClosureAlbum(AlbumConfig(max_frame_bytes=1000), VerificationConfig(), wire.load)
    for stamp in range(15):
        album.add_frame(stamp, wire.serialize(str(stamp), _frame(stamp), size=100))
    assert album.frames.nbytes <= 1000 and len(album.frames) == 10
    assert list(range(5)) == [stamp for stamp in range(15) if stamp not in album.frames]


def test_a_frame_that_does_not_decode_raises_data_error():
    wire = FakeWire()
    album = ClosureAlbum(AlbumConfig(), VerificationConfig(), wire.load)
    album.add_frame(1, wire.serialize("1", _frame(1)))
    album.add_frame(2, b"garbage")
    with pytest.raises(DataError):
        album.picture(2, 1, "q", refused=False)


def test_a_thumbnail_of_another_width_than_the_image_scales_the_keypoints():
    """An image 640 wide shown as a 320-wide thumbnail: a keypoint at x=400 is drawn at x=200."""
    from aefabmap_ros.visualization.match_picture import PairMatches, closure_picture

    black = encode_jpeg(np.zeros((240, 320), np.uint8))
    matches = PairMatches(np.array([[400.0, 200.0]], np.float32), np.array([[400.0, 200.0]], np.float32),
                          np.array([False]))  # an outlier: one red dot at each end
    drawn = decode_jpeg(closure_picture((black, 640), (black, 640), matches, "", refused=False))
    canvas = drawn[drawn.shape[0] - 240:]
    assert canvas[100, 200, 2] > 120 and canvas[100, 320 + 200, 2] > 120
    assert canvas[200, 400, 2] < 60  # nothing where the unscaled point would be
