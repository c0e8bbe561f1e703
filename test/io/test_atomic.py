from pathlib import Path

import pytest

from aefabmap_ros.io.atomic import atomic_open, atomic_write_bytes, remove_stale_temporaries


def test_temporaries_of_killed_writes_are_removed_and_nothing_else(tmp_path: Path) -> None:
    atomic_write_bytes(tmp_path / "map.npz", b"the map")
    killed = [tmp_path / ".map.npz.a1b2c3.tmp", tmp_path / ".chunk-000000003.npz.zz.tmp"]
    kept = [tmp_path / ".other.npz.a1.tmp", tmp_path / "map.npz", tmp_path / ".map.npz.notes"]
    for path in killed + kept[:1] + kept[2:]:
        path.write_bytes(b"x")
    assert remove_stale_temporaries(tmp_path, "map.npz") == [killed[0]]
    assert remove_stale_temporaries(tmp_path, "chunk-*.npz") == [killed[1]]
    assert all(path.exists() for path in kept) and not any(path.exists() for path in killed)
    assert remove_stale_temporaries(tmp_path / "missing", "map.npz") == []


def test_atomic_open_replaces_on_success_and_keeps_the_old_file_on_error(tmp_path):
    target = tmp_path / "features.npz"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_open(target) as file:
        file.write(b"half of the new")
        raise RuntimeError("writer failed")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["features.npz"]  # no temporary left behind
    with atomic_open(target) as file:
        file.write(b"new")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["features.npz"]


def test_a_save_keeps_the_files_mode_and_a_new_file_gets_the_umasks(tmp_path: Path) -> None:
    """tempfile.mkstemp makes 0600 files: a 0644 map must not turn 0600 (unreadable to the group) by a save."""
    import os
    import stat

    def mode(path: Path) -> int:
        return stat.S_IMODE(path.stat().st_mode)

    for existing in (0o644, 0o640, 0o600, 0o664, 0o444):
        target = tmp_path / f"map_{existing:o}.npz"
        target.write_bytes(b"old")
        target.chmod(existing)
        atomic_write_bytes(target, b"new")
        assert target.read_bytes() == b"new" and mode(target) == existing, f"{existing:o} -> {mode(target):o}"
    previous = os.umask(0o022)
    try:
        for umask, expected in ((0o022, 0o644), (0o077, 0o600), (0o002, 0o664)):
            os.umask(umask)
            fresh = tmp_path / f"fresh_{umask:o}.npz"
            with atomic_open(fresh) as file:
                file.write(b"first")
            assert mode(fresh) == expected, f"umask {umask:o}: {mode(fresh):o}"
    finally:
        os.umask(previous)
