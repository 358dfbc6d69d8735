"""Pack a Minari dataset of stacked frames small enough to carry to the device machine, and unpack it there.

The device machine takes the working tree and at most 64 MiB beside it. A frame-stacked Atari dataset is mostly the
same frames four times over (`observations[t, 1:] == observations[t - 1, :-1]`), then gzip: `gmt/breakout/react-v1`
is 69 MiB on disk. Packed, each episode keeps its first stack and the newest frame of every later step, compressed
with LZMA in chunks of episodes (5 MiB for that dataset); everything else in the HDF5 file is copied as it is.
Unpacking rebuilds byte-identical arrays (the dataset's fingerprint is unchanged), written uncompressed so that
loading is fast.

    python -m research.carry_dataset pack data/minari/gmt/breakout/react-v1 .devdata/react-v1
    python -m research.carry_dataset unpack .devdata/react-v1 data/minari/gmt/breakout/react-v1 --workers 16
"""

from __future__ import annotations

import argparse
import json
import lzma
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import h5py
import numpy as np

MAIN = "main_data.hdf5"
SKELETON = "skeleton.hdf5"
INDEX = "frames.json"


def is_stacked(obs: np.ndarray) -> bool:
    """Whether `obs` [T, S, ...] is a frame stack that shifts by one frame a step."""
    return obs.ndim >= 3 and obs.shape[1] > 1 and bool((obs[1:, :-1] == obs[:-1, 1:]).all())


def to_stream(obs: np.ndarray) -> np.ndarray:
    """[T, S, ...] stacks -> [T + S - 1, ...] frames: the first stack, then each step's newest frame."""
    return np.concatenate([obs[0, :-1], obs[:, -1]])


def from_stream(frames: np.ndarray, S: int) -> np.ndarray:
    """Inverse of `to_stream`: [T + S - 1, ...] frames -> [T, S, ...] stacks."""
    win = np.lib.stride_tricks.sliding_window_view(frames, S, axis=0)  # [T, ..., S]
    return np.ascontiguousarray(np.moveaxis(win, -1, 1))  # [T, S, ...]


def pack(src: Path, dst: Path, chunk: int = 32, preset: int = 6) -> dict:
    """Pack the Minari dataset directory `src` (holding data/) into `dst`.

    Returns:
        The index written to dst/frames.json: per episode its stack size (0 = stored whole) and shape.
    """
    dst.mkdir(parents=True, exist_ok=True)
    shutil.copy(src / "data" / "metadata.json", dst / "metadata.json")
    index: dict = {"chunk": chunk, "episodes": {}}
    with h5py.File(src / "data" / MAIN, "r") as f, h5py.File(dst / SKELETON, "w") as sk:
        sk.attrs.update(dict(f.attrs))
        names = sorted(f.keys(), key=lambda n: int(n.split("_")[-1]) if n.split("_")[-1].isdigit() else -1)
        for c in range(0, len(names), chunk):
            parts = []
            for name in names[c : c + chunk]:
                ep = f[name]
                g = sk.create_group(name)
                g.attrs.update(dict(ep.attrs))
                for key in ep:
                    if key != "observations":
                        f.copy(ep[key], g, name=key)
                obs = ep["observations"][()]
                stacked = is_stacked(obs)
                parts.append(to_stream(obs) if stacked else obs)
                index["episodes"][name] = {
                    "stack": obs.shape[1] if stacked else 0,
                    "shape": list(obs.shape),
                    "dtype": str(obs.dtype),
                    "attrs": {k: v.tolist() for k, v in ep["observations"].attrs.items()},
                }
            blob = b"".join(np.ascontiguousarray(p).tobytes() for p in parts)
            (dst / f"frames-{c // chunk:04d}.xz").write_bytes(lzma.compress(blob, preset=preset))
    (dst / INDEX).write_text(json.dumps(index))
    return index


def _unpack_chunk(args: tuple[Path, list[str], dict]) -> dict[str, np.ndarray]:
    path, names, episodes = args
    blob, out, at = lzma.decompress(path.read_bytes()), {}, 0
    for name in names:
        e = episodes[name]
        shape, S = e["shape"], e["stack"]
        stored = [shape[0] + S - 1, *shape[2:]] if S else shape
        n = int(np.prod(stored)) * np.dtype(e["dtype"]).itemsize
        arr = np.frombuffer(blob[at : at + n], dtype=e["dtype"]).reshape(stored)
        at += n
        out[name] = from_stream(arr, S) if S else arr.copy()
    return out


def unpack(src: Path, dst: Path, workers: int = 1) -> int:
    """Rebuild the Minari dataset directory `dst` (data/main_data.hdf5 + metadata.json) from a pack.

    Returns:
        The number of episodes written.
    """
    index = json.loads((src / INDEX).read_text())
    names = list(index["episodes"])
    chunk = index["chunk"]
    jobs = [
        (src / f"frames-{i:04d}.xz", names[c : c + chunk], index["episodes"])
        for i, c in enumerate(range(0, len(names), chunk))
    ]
    (dst / "data").mkdir(parents=True, exist_ok=True)
    shutil.copy(src / "metadata.json", dst / "data" / "metadata.json")
    main = dst / "data" / MAIN
    shutil.copy(src / SKELETON, main)
    with h5py.File(main, "r+") as f, ProcessPoolExecutor(max(workers, 1)) as pool:
        for arrays in pool.map(_unpack_chunk, jobs):
            for name, obs in arrays.items():
                ds = f[name].create_dataset("observations", data=obs)
                ds.attrs.update(index["episodes"][name]["attrs"])
    return len(names)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack", help="pack a Minari dataset directory")
    p.add_argument("src", type=Path, help="the dataset directory (holding data/main_data.hdf5)")
    p.add_argument("dst", type=Path, help="the pack directory to write")
    p.add_argument("--chunk", type=int, default=32, help="episodes per compressed file")
    u = sub.add_parser("unpack", help="rebuild a Minari dataset directory from a pack")
    u.add_argument("src", type=Path, help="the pack directory")
    u.add_argument("dst", type=Path, help="the dataset directory to write")
    u.add_argument("--workers", type=int, default=1, help="processes decompressing chunks")
    a = ap.parse_args()
    if a.cmd == "pack":
        idx = pack(a.src, a.dst, a.chunk)
        size = sum(p.stat().st_size for p in a.dst.iterdir())
        print(f"packed {len(idx['episodes'])} episodes into {a.dst} ({size / 2**20:.1f} MiB)")
    else:
        n = unpack(a.src, a.dst, a.workers)
        print(f"unpacked {n} episodes into {a.dst}")


if __name__ == "__main__":
    main()
