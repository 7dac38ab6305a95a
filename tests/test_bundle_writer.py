"""BundleWriter.discard: work files leave the bundle at once and are deleted on a thread, whether
the bundle is finished or the run fails."""

import pytest

from dmrt.io.bundle import BundleWriter


def _work(folder):
    (folder / "work" / "level_00").mkdir(parents=True)
    (folder / "work" / "level_00" / "positions.bin").write_bytes(b"\0" * 4096)
    return folder / "work"


def test_discarded_work_is_gone_from_the_bundle_and_the_disk(tmp_path):
    out = tmp_path / "b"
    with BundleWriter(out) as bw:
        work = _work(bw.tmp)
        bw.discard(work)
        assert not work.exists()  # out of the bundle before its deletion ends
        bw.wait_discarded()
        bw.finish({})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]  # no trash left beside it
    assert not (out / "work").exists() and (out / "bundle.json").is_file()


def test_a_failed_run_waits_for_the_deletion_and_leaves_nothing(tmp_path):
    (tmp_path / ".b.discarded" / "0").mkdir(parents=True)  # left by a run that was killed
    with pytest.raises(KeyError):
        with BundleWriter(tmp_path / "b") as bw:
            bw.discard(_work(bw.tmp))
            raise KeyError("the run fails")
    assert list(tmp_path.iterdir()) == []
