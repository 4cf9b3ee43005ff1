"""The packed frame store's container and codec: Zarr v3 (ringscan's store) against Blosc2's own format.

For one view's 28 frames (a full-size simulated view, and 28 frames of a real capture
from shared/data/procam), prints per candidate: size on disk, and the best-of-N time to
read all frames into memory on one thread (files read from the page cache, decoded),
next to PNG as OpenCV writes it by default and to copying the frames in memory (the
floor). Blosc2's own format needs ``pip install blosc2`` (not a ringscan dependency).
With zarr-python installed (``pip install '.[test]'``), the same store read through it
too, and its read time against ringscan's in ``--rounds`` interleaved rounds, alone and
behind ringscan's own checks, and writing the store both ways (issue 36 item 5: zarr-python's
reader unless > 1.2x slower; the figures are in :mod:`ringscan.pipeline.formats.frame_store`'s
docstring).

Then the Blosc settings a Zarr v3 store can hold (:data:`CODECS`: codec, level, shuffle,
block size), on both frame sets, measured in interleaved rounds (the machine is shared:
each candidate once per round, the best of the rounds kept): size against the PNG,
decoding the 28 chunks on one thread into a preallocated stack, and that time against
two memory floors: copying the frames into a preallocated, already-faulted stack
(``np.copyto``: a reader that reuses its output) and into a fresh one (``np.empty`` +
copy: what :func:`~ringscan.pipeline.formats.frame_store.read_store` does, the stack
being new for each view), and the seconds to encode a frame (capture, ``ringscan pack``).

Usage::

    python benchmarks/frame_store.py [--scan SCAN_FOLDER] [--procam ../shared/data/procam/capture_1] [--rounds 7]

``--scan``: a full-size scan folder with PNG frames (default: one view simulated with
``ringscan simulate`` into /tmp/ringscan_frame_store, kept for reruns).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.formats import frame_store as fs
from ringscan.pipeline.formats.scan import load_scan, read_view_frames

REPS = 7
CODECS = (("zstd", 5, "bit", 0), ("zstd", 5, "bit", 1 << 20), ("zstd", 1, "bit", 0), ("zstd", 3, "bit", 0),
          ("zstd", 3, "bit", 256 << 10), ("zstd", 7, "bit", 0), ("zstd", 9, "bit", 0),
          ("lz4hc", 9, "bit", 0), ("lz4hc", 9, "bit", 64 << 10), ("lz4hc", 9, "bit", 1 << 20), ("lz4hc", 5, "bit", 0),
          ("lz4hc", 1, "bit", 0), ("lz4", 9, "bit", 0), ("lz4", 5, "bit", 0), ("blosclz", 9, "bit", 0),
          ("zstd", 1, "byte", 0), ("lz4", 9, "byte", 0))
"""Blosc settings compared (cname, clevel, shuffle, blocksize; 0: Blosc's own choice). For 8-bit frames
byte-shuffle moves nothing (one byte per element): it is the no-shuffle case."""


def best(f, reps: int = REPS) -> float:
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return min(ts)


def size_of(p: Path) -> int:
    return p.stat().st_size if p.is_file() else sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def blosc2_candidates(frames: np.ndarray, tmp: Path) -> list[tuple[str, Path, callable]]:
    """Blosc2's own format (.b2nd, one chunk per frame): the codecs worth comparing."""
    try:
        import blosc2
    except ImportError:
        print("   (blosc2 not installed: Blosc2's own format skipped)")
        return []
    blosc2.set_nthreads(1)
    out = []
    F, C = blosc2.Filter, blosc2.Codec
    for label, codec, level, filt in (("zstd 5, bit-shuffle", C.ZSTD, 5, F.BITSHUFFLE),
                                      ("zstd 1, no filter", C.ZSTD, 1, F.NOFILTER),
                                      ("zstd 1, shuffle + byte-delta", C.ZSTD, 1, F.BYTEDELTA),
                                      ("lz4hc 5, bit-shuffle", C.LZ4HC, 5, F.BITSHUFFLE),
                                      ("lz4 1, bit-shuffle", C.LZ4, 1, F.BITSHUFFLE)):
        path = tmp / f"b2_{codec.name}_{level}_{filt.name}.b2nd"
        filters = [F.SHUFFLE, F.BYTEDELTA] if filt == F.BYTEDELTA else [filt]
        blosc2.asarray(frames, chunks=(1,) + frames.shape[1:], urlpath=str(path), mode="w",
                       cparams={"codec": codec, "clevel": level, "filters": filters, "nthreads": 1},
                       dparams={"nthreads": 1})

        def read(path=path):
            return blosc2.open(str(path), mode="r", dparams={"nthreads": 1})[:]

        assert np.array_equal(read(), frames)
        out.append((f"Blosc2 .b2nd, {label}", path, read))
    return out


def zarr_ratio(info, zarr_read, rounds: int) -> str:
    """Issue 36 item 5's figures: zarr-python's read of a view against ringscan's, in interleaved
    rounds (each reader once per round, the best of the rounds kept: the machine is shared): on
    one thread as the table reads it (zarr-python alone), the same behind ringscan's own checks
    (zarr.json, and every chunk file's presence, kind, size and Blosc header: a read through
    zarr-python would need them first, as it fills a missing chunk with zeros), and on all cores
    (ringscan's ``threads`` = the CPU count against zarr-python's default concurrency). Then writing
    the view both ways (the same codecs, chunks and attributes), best of 3, the chunk files compared."""
    import os

    import zarr

    cores = os.cpu_count() or 1

    def checked():
        fs.check_chunk_files(fs.open_store(info.path), info.names)
        return zarr_read()

    readers = {"ringscan": lambda: fs.read_store(info.path), "zarr": zarr_read, "checked": checked,
               "ringscan, all cores": lambda: fs.read_store(info.path, threads=cores),
               "zarr, all cores": lambda: zarr.open_array(str(info.path), mode="r")[...]}
    ts: dict = {k: [] for k in readers}
    for _ in range(rounds):
        for k, f in readers.items():
            t = time.perf_counter()
            f()
            ts[k].append(time.perf_counter() - t)
    t = {k: min(v) for k, v in ts.items()}
    # writing: ringscan's write_store (atomic chunks, read back and compared) against zarr-python writing
    # the same layout (codecs, chunks, attributes) on one thread; the chunk files must come out identical
    frames = fs.read_store(info)
    dtype = frames.dtype

    def zarr_write(path):
        z = zarr.create_array(str(path), shape=frames.shape, chunks=(1,) + frames.shape[1:], dtype=dtype.name,
                              serializer=zarr.codecs.BytesCodec(endian="little"),
                              compressors=[zarr.codecs.BloscCodec(typesize=dtype.itemsize, **fs.BLOSC),
                                           zarr.codecs.Crc32cCodec()],
                              attributes={"ringscan": {"format": fs.STORE_FORMAT, "frames": list(info.names)}},
                              dimension_names=["frame", "y", "x"], fill_value=0, overwrite=True)
        with zarr.config.set({"async.concurrency": 1}):
            z[...] = frames

    w: dict = {"ringscan": [], "zarr": []}
    for _ in range(3):
        for k, f in (("ringscan", lambda: fs.write_store(info.path.parent / "w_ours.zarr", frames, info.names)),
                     ("zarr", lambda: zarr_write(info.path.parent / "w_zarr.zarr"))):
            t0 = time.perf_counter()
            f()
            w[k].append(time.perf_counter() - t0)
    same = all((info.path.parent / d / "c" / str(i) / "0" / "0").read_bytes() == info.chunk_path(i).read_bytes()
               for d in ("w_ours.zarr", "w_zarr.zarr") for i in range(len(info.names)))
    return (f"   zarr-python / ringscan, reading the view (best of {rounds} interleaved rounds): one thread "
            f"{1000 * t['zarr']:.1f} / {1000 * t['ringscan']:.1f} ms = {t['zarr'] / t['ringscan']:.2f}x, behind "
            f"ringscan's checks {1000 * t['checked']:.1f} ms = {t['checked'] / t['ringscan']:.2f}x; {cores} cores "
            f"{1000 * t['zarr, all cores']:.1f} / {1000 * t['ringscan, all cores']:.1f} ms = "
            f"{t['zarr, all cores'] / t['ringscan, all cores']:.2f}x\n"
            f"   writing the view (best of 3): zarr-python {1000 * min(w['zarr']):.0f} ms, ringscan (its read-back "
            f"included) {1000 * min(w['ringscan']):.0f} ms; chunk files {'identical' if same else 'DIFFERENT'}")


def measure(label: str, frames: np.ndarray, png_read, rounds: int = REPS) -> None:
    import numcodecs.blosc

    numcodecs.blosc.use_threads = False  # Blosc on the calling thread alone
    tmp = Path(tempfile.mkdtemp(prefix="ringscan_fs_"))
    try:
        copy = np.empty_like(frames)
        floor = best(lambda: np.copyto(copy, frames))
        pngs = [cv2.imencode(".png", f)[1] for f in frames]  # OpenCV's default PNG parameters
        for i, b in enumerate(pngs):
            (tmp / f"{i}.png").write_bytes(b.tobytes())
        t_png = best(lambda: [cv2.imread(str(tmp / f"{i}.png"), cv2.IMREAD_UNCHANGED) for i in range(len(pngs))], 3)
        size_png = sum(len(b) for b in pngs)
        info = fs.write_store(tmp / "frames.zarr", frames, [f"f{i}" for i in range(len(frames))])
        rows = [("PNG, OpenCV's default parameters", size_png, t_png)]
        ratio = ""
        rows.append(("Zarr v3 (ringscan): Blosc zstd 5, bit-shuffle, CRC32C", size_of(tmp / "frames.zarr"),
                     best(lambda: fs.read_store(info))))
        try:  # the same store through zarr-python v3 (issue 36: a library's reader unless > 1.2x slower)
            import zarr

            def zarr_read():
                with zarr.config.set({"async.concurrency": 1}):  # one chunk at a time: one core
                    return zarr.open_array(str(tmp / "frames.zarr"), mode="r")[...]

            assert np.array_equal(zarr_read(), frames)
            rows.append((f"the same store through zarr-python {zarr.__version__} (1 thread)",
                         size_of(tmp / "frames.zarr"), best(zarr_read)))
            ratio = zarr_ratio(info, zarr_read, rounds)
        except ImportError:
            print("zarr-python is not installed (pip install '.[test]'): its reader not measured")
        if png_read is not None:
            rows.append(("ringscan's PNG (read_view_frames, 1 thread)", png_read[0], best(png_read[1], 3)))
        for name, path, read in blosc2_candidates(frames, tmp):
            rows.append((name, size_of(path), best(read)))
        print(f"\n{label}: {frames.shape[0]} frames {frames.shape[2]}x{frames.shape[1]} {frames.dtype}, "
              f"{frames.nbytes / 1e6:.1f} MB in memory; copying them in memory {1000 * floor:.1f} ms")
        print("   | container, codec | size | vs PNG (OpenCV) | read, 1 thread | vs PNG | vs the copy |")
        print("   |---|---|---|---|---|---|")
        for name, size, t in rows:
            print(f"   | {name} | {size / 1e6:.1f} MB | {size / size_png:.2f}x | {1000 * t:.1f} ms | "
                  f"{t_png / t:.1f}x faster | {t / floor:.1f}x |")
        if ratio:
            print(ratio)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        numcodecs.blosc.use_threads = None


def codec_sweep(sets: dict[str, np.ndarray], rounds: int) -> None:
    """The Blosc settings of :data:`CODECS` on every frame set, interleaved rounds (module docstring)."""
    import numcodecs.blosc
    from numcodecs import Blosc

    numcodecs.blosc.use_threads = False  # Blosc on the calling thread alone
    shuffles = {"bit": Blosc.BITSHUFFLE, "byte": Blosc.SHUFFLE, "none": Blosc.NOSHUFFLE}
    rows: dict = {c: {} for c in CODECS}
    floors: dict = {}
    for label, frames in sets.items():
        png = sum(len(cv2.imencode(".png", f)[1]) for f in frames)
        out = np.zeros_like(frames)
        hot = np.zeros_like(frames)
        enc, t_enc = {}, {}
        for c in CODECS:
            codec = Blosc(cname=c[0], clevel=c[1], shuffle=shuffles[c[2]], blocksize=c[3])
            t = time.perf_counter()
            enc[c] = [bytes(codec.encode(f)) for f in frames]
            t_enc[c] = (time.perf_counter() - t) / len(frames)
        dec = Blosc()
        ts: dict = {c: [] for c in CODECS}
        f_hot, f_fresh = [], []
        for _ in range(rounds):
            for c in CODECS:
                t = time.perf_counter()
                for chunk, o in zip(enc[c], out):
                    dec.decode(chunk, out=o)
                ts[c].append(time.perf_counter() - t)
                t = time.perf_counter()
                np.copyto(hot, frames)
                f_hot.append(time.perf_counter() - t)
                t = time.perf_counter()
                np.copyto(np.empty_like(frames), frames)
                f_fresh.append(time.perf_counter() - t)
        assert np.array_equal(out, frames)
        floors[label] = (min(f_hot), min(f_fresh))
        for c in CODECS:
            size = sum(len(e) + 4 for e in enc[c])  # + each chunk's CRC32C
            rows[c][label] = (size / png, min(ts[c]), t_enc[c])
    print(f"\nBlosc settings (decode on one thread, best of {rounds} interleaved rounds; floors: copy into a "
          "preallocated stack / into a fresh one):")
    for label, (fh, ff) in floors.items():
        print(f"   {label}: floors {1000 * fh:.1f} / {1000 * ff:.1f} ms")
    head = " | ".join(f"{label}: size vs PNG | decode | vs floors | encode a frame" for label in sets)
    print(f"   | cname, clevel, shuffle, blocksize | {head} |")
    print("   |---|" + "---|---|---|---|" * len(sets))
    for c, per in rows.items():
        cells = []
        for label, (ratio, t, te) in per.items():
            fh, ff = floors[label]
            cells.append(f"{ratio:.3f}x | {1000 * t:.1f} ms | {t / fh:.1f}x / {t / ff:.1f}x | {1000 * te:.0f} ms")
        bs = f"{c[3] >> 10} KiB" if c[3] else "auto"
        print(f"   | {c[0]} {c[1]}, {c[2]}-shuffle, {bs} | " + " | ".join(cells) + " |")
    numcodecs.blosc.use_threads = None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", default=None, help="a full-size scan folder with PNG frames")
    ap.add_argument("--procam", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "procam"
                                            / "capture_1"))
    ap.add_argument("--rounds", type=int, default=REPS,
                    help="interleaved rounds of the codec table and of zarr-python's read against ringscan's "
                         "(default 7)")
    a = ap.parse_args()
    scan_dir = Path(a.scan) if a.scan else Path("/tmp/ringscan_frame_store/scan")
    if not (scan_dir / "scan.json").is_file():
        print(f"simulating one full-size view into {scan_dir} ...", flush=True)
        subprocess.run([sys.executable, "-m", "ringscan.tools.cli", "simulate", "--out", str(scan_dir),
                        "--no-progress", "--device", "cpu"], check=True)
    scan = load_scan(scan_dir)
    view = scan.views[0]
    frames = read_view_frames(scan, view, threads=1)
    png_size = sum(size_of(scan.frame_path(view, n)) for n in view.frames) if view.packed is None else None
    measure(f"simulated view ({scan_dir})", frames,
            (png_size, lambda: read_view_frames(scan, view, threads=1)) if png_size else None, a.rounds)
    sets = {"simulated": frames}
    procam = sorted(Path(a.procam).glob("graycode_*.png"))[:28]
    if len(procam) == 28:
        sets["real capture"] = np.stack([cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in procam])
        measure(f"real capture ({a.procam}, graycode_00..27)", sets["real capture"], None, a.rounds)
    else:
        print(f"\n(real captures not found at {a.procam}: skipped)")
    codec_sweep(sets, a.rounds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
