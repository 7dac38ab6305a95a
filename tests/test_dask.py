"""Preprocessing on Dask (``dmrt preprocess --dask``): a real 3-worker LocalCluster (no mock), 2 of
whose workers render the depth maps, gives the in-process bundle, bit for bit."""

import ctypes
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from dmrt.app.cli import main
from dmrt.errors import ConfigError
from dmrt.io.bundle import read_bundle
from dmrt.preprocess.parallel import _gpu_workers, _nvidia_gpus, _spread_gpus, open_executor, split
from dmrt.preprocess.pipeline import PreprocessConfig, _read_ahead, preprocess
from helpers import assert_bundles_equal


@pytest.fixture(scope="module")
def executor():
    """Three worker processes of one thread each, the first two (by rank) GPU workers: each of those
    makes its own EGL context (llvmpipe here), as on a 2-GPU host with more cores than GPUs."""
    with open_executor("local:3", gpus_per_host=2) as ex:
        assert ex.workers == 3 and len(ex.gpu_workers) == 2
        yield ex


def _has_gl_context():
    from dmrt.gl import context

    return context._shared is not None


@pytest.mark.slow
@pytest.mark.e2e
def test_dask_bundle_equals_in_process(tiny_scene, tiny_bundle, executor, tmp_path):
    out = preprocess(tiny_scene, tmp_path / "tiny", PreprocessConfig(depthmap_width=256), progress=False,
                     executor=executor)
    a, b = read_bundle(tiny_bundle), read_bundle(out)
    # exactly the two GPU workers rendered depth maps (every map, each from half of P_HD: two shares)
    # on a GL context of their own; the third ran CPU tasks only
    has_gl = executor.client.run(_has_gl_context)
    assert sorted(a for a, gl in has_gl.items() if gl) == sorted(executor.gpu_workers) and len(has_gl) == 3
    # (the tiny cloud fits --memory-limit-mb, so its normals/radii are one in-memory pass here; the
    # bucketed path's tasks are checked below)
    # everything is computed by the same code on the same inputs, only in other processes: no
    # floating-point order differs (P_HD is cut into ranges and each map merged as the nearest depth
    # of the ranges' maps, exact since a map holds each texel's nearest splat; candidates are joined
    # in photo order before the rim rule; labeling is global), so bit for bit
    assert_bundles_equal(a, b)
    assert b.meta["dask"] == {"spec": "local:3", "workers": 3, "gpu_workers": 2} and "dask" not in a.meta


def test_gpu_workers(executor):
    """Per host, the first workers by rank: as many as asked, else as the host's NVIDIA GPUs (at
    least 1: llvmpipe renders on one worker), never more than the host's workers."""
    ranks = _spread_gpus(executor.client)  # the ranks open_executor gave (it pins nothing twice)
    by_rank = sorted(ranks, key=ranks.get)
    assert sorted(ranks.values()) == [0, 1, 2] and executor.gpu_workers == by_rank[:2]
    assert _gpu_workers(executor.client, ranks, None) == by_rank[:max(1, min(_nvidia_gpus(), 3))]
    assert _gpu_workers(executor.client, ranks, 1) == by_rank[:1]
    assert _gpu_workers(executor.client, ranks, 8) == by_rank
    with pytest.raises(ValueError, match="3 GPU tasks for 2 GPU workers"):
        executor.map_gpus(int, [1, 2, 3])
    # one item per GPU worker, on that worker only
    where = executor.map_gpus(_worker_address, [0, 1])
    assert where == executor.gpu_workers


def _worker_address(_):
    from distributed import get_worker

    return get_worker().address


class _MallInfo2(ctypes.Structure):  # glibc's struct mallinfo2 (size_t fields)
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


def _mmapped_blocks_of_new_arrays() -> int:
    """Of four 1 MiB arrays made and dropped in turn (as the depth-map phase's chunks are), how
    many glibc mmapped (its count of mmapped blocks, ``mallinfo2().hblks``, rose)."""
    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = _MallInfo2
    mapped = 0
    for _ in range(4):
        before = libc.mallinfo2().hblks
        a = np.ones(1 << 18, np.float32)
        mapped += libc.mallinfo2().hblks > before
        del a
    return mapped


def test_workers_reuse_the_heap(executor):
    """The nanny's MALLOC_TRIM_THRESHOLD_ makes every array above 128 KiB a fresh mmap in a
    worker process; open_executor fixes glibc's thresholds there (_plain_heap), so that 1 MiB
    arrays come from the heap again, as in a plain process."""
    code = ("import test_dask as t; from dmrt.preprocess.parallel import _plain_heap; "
            "print(t._mmapped_blocks_of_new_arrays(), _plain_heap(), t._mmapped_blocks_of_new_arrays())")
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536",
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), str(Path(__file__).parents[1])])}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["4", "True", "0"]  # a fresh mmap per array with the variable alone, none after
    assert set(executor.client.run(_mmapped_blocks_of_new_arrays).values()) == {0}


def test_read_ahead_same_items_no_leaked_thread():
    """The depth maps' chunk reader: the same items in order, re-callable, errors raised in the
    consumer, and no thread left behind when the consumer stops early."""
    before = threading.active_count()
    assert list(_read_ahead(iter(range(7)))) == list(range(7))
    assert list(_read_ahead(iter([]), depth=1)) == []
    stopped = _read_ahead(iter(range(100)))
    assert next(stopped) == 0
    del stopped  # dropped half read, as render_many drops the reader when the cloud exceeds its budget
    assert threading.active_count() == before

    def failing():
        yield 1
        raise OSError("disk gone")

    with pytest.raises(OSError, match="disk gone"):
        list(_read_ahead(failing()))
    assert threading.active_count() == before


@pytest.mark.slow
@pytest.mark.e2e
def test_process_pool_bundle_equals_in_process(tiny_scene, tiny_bundle, tmp_path):
    """The default on one machine: the CPU phases in 2 spawned processes, depth maps here."""
    with open_executor(None, workers=2) as ex:
        assert ex.distributed and not ex.gpu_tasks
        out = preprocess(tiny_scene, tmp_path / "tiny", PreprocessConfig(depthmap_width=256), progress=False,
                         executor=ex)
    a, b = read_bundle(tiny_bundle), read_bundle(out)
    assert_bundles_equal(a, b)  # as on Dask: the same code on the same inputs
    assert b.meta["processes"] == {"spec": "processes:2", "workers": 2} and "processes" not in a.meta


@pytest.mark.slow
def test_bucketed_normals_as_tasks(tiny_scene, executor, tmp_path):
    """Normals/radii out of core (a budget far below the cloud: many buckets), per bucket as tasks."""
    from dmrt.io.scene import load_scene
    from dmrt.preprocess.normals import process_chunked

    scene = load_scene(tiny_scene)
    pos = scene.read_points().positions[::4] - scene.origin  # 50k points
    chunks = lambda: ((pos[s:s + 10_000], {}) for s in range(0, len(pos), 10_000))  # noqa: E731
    kw = dict(normals=True, radii=True, viewpoints=np.array([c.center for c in scene.cameras]) - scene.origin,
              memory_limit_mb=4, progress=False)
    here = process_chunked(chunks, tmp_path / "here", **kw)
    there = process_chunked(chunks, tmp_path / "there", executor=executor, **kw)
    assert here.n_buckets > 2 and (here.n_buckets, here.n_unverified) == (there.n_buckets, there.n_unverified)
    # each bucket's kNN and plane fits are the same code on the same points: bit for bit
    assert np.array_equal(here.normals, there.normals) and np.array_equal(here.radii, there.radii)


@pytest.mark.slow
def test_dmt_labels_as_tasks(tiny_bundle, executor, tmp_path):
    from baselines.dmt.labeling import dmt_labels

    bundle_dir = tmp_path / "b"
    shutil.copytree(tiny_bundle, bundle_dir, ignore=shutil.ignore_patterns("dmt"))
    bundle = read_bundle(bundle_dir)
    here, meta = dmt_labels(bundle, 32, progress=False, recompute=True)
    there, meta2 = dmt_labels(bundle, 32, progress=False, recompute=True, executor=executor)
    assert len(here) == len(there) and all(np.array_equal(x, y) for x, y in zip(here, there))
    assert meta["energy"] == meta2["energy"]


def test_split():
    assert split(12, 2) == [range(0, 6), range(6, 12)]
    assert split(3, 5) == [range(0, 1), range(1, 2), range(2, 3)]
    assert [len(r) for r in split(10, 3)] == [3, 3, 4]


@pytest.mark.parametrize("spec", ["local:two", "local:0", "udp://host:8786", "tcp://host", "8786"])
def test_bad_spec(spec):
    with pytest.raises(ConfigError, match="--dask"):
        with open_executor(spec):
            pass


@pytest.mark.parametrize("args, message", [
    (["--dask-gpus", "2"], "--dask-gpus: needs --dask"),
    (["--dask", "local:2", "--dask-gpus", "0"], "--dask-gpus: must be >= 1, not 0"),
])
def test_bad_dask_gpus_exit_2_one_line(tmp_path, capsys, args, message):
    assert main(["preprocess", str(tmp_path / "scene"), "--out", str(tmp_path / "b"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(f"dmrt: error: {message}")
    assert not (tmp_path / "b").exists()


def test_bad_spec_exit_2_one_line(tmp_path, capsys):
    assert main(["preprocess", str(tmp_path / "scene"), "--out", str(tmp_path / "b"), "--dask", "locl:2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("dmrt: error: --dask: 'locl:2': expected local:N")
    assert not (tmp_path / "b").exists()
