"""Atomic writes (dmrt.io.atomic): a file or folder appears under its final name only when whole,
with the permissions a plain open() would give it."""

import os

import pytest

from dmrt.errors import InputError
from dmrt.io.atomic import atomic_dir, atomic_file, write_text


def test_file_appears_whole_with_the_umask_mode(tmp_path):
    mask = os.umask(0o022)
    try:
        path = write_text(tmp_path / "sub" / "a.txt", "hello")
    finally:
        os.umask(mask)
    assert path.read_text() == "hello" and path.stat().st_mode & 0o777 == 0o644
    with pytest.raises(RuntimeError), atomic_file(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert path.read_text() == "hello"  # the old file stands; no temporary file is left
    assert sorted(p.name for p in path.parent.iterdir()) == ["a.txt"]


def test_folder_is_renamed_into_place_or_refused(tmp_path):
    out = tmp_path / "bundle"
    with atomic_dir(out, what="bundle") as tmp:
        (tmp / "x").write_text("1")
        assert not out.exists()
    assert (out / "x").read_text() == "1"
    with pytest.raises(InputError, match="bundle already exists"):
        with atomic_dir(out, force=False, what="bundle"):
            pass
    with pytest.raises(RuntimeError), atomic_dir(out) as tmp:
        (tmp / "y").write_text("2")
        raise RuntimeError("interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle"] and (out / "x").exists()
    with atomic_dir(out) as tmp:
        (tmp / "z").write_text("3")
    assert sorted(p.name for p in out.iterdir()) == ["z"]
