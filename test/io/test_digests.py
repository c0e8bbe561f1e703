import hashlib

from aefabmap_ros.io.digests import file_sha256


def test_file_sha256_is_the_sha256_of_the_bytes_across_chunks(tmp_path):
    data = bytes(range(256)) * 5000  # > 1 MiB: more than one read
    path = tmp_path / "weights.pt"
    path.write_bytes(data)
    assert file_sha256(path) == hashlib.sha256(data).hexdigest()
