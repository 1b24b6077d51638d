"""``clflow bench write``: what writing a result all or nothing costs beside its bytes."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option


@bench_command("write")
@click.option("--gb", type=click.FloatRange(min=0.001, max=64), default=1.0, show_default=True,
              help="Size of the result (GB = 1e9 bytes).")  # fmt: skip
@count_option("--files", default=100, help="Files the result is split into.")
@click.option("--in", "where", type=click.Path(file_okay=False, exists=True), default=".", show_default=True,
              help="Folder to write in (its disk is what is measured; /tmp may be memory).")  # fmt: skip
@count_option("--repeat", default=3, help="Timed writes (median reported).")
def write(gb: float, files: int, where: str, repeat: int) -> dict:
    """Seconds to write a result of GB in FILES files: its bytes alone (with and without
    fsync), through clflow.fileio.atomic_dir over the earlier result (check, digests, sync,
    journal, moves, record), and the parts: a check of the earlier result by fingerprint and
    by digest (as after a copy), the digests, the lock."""
    import os
    import shutil
    import statistics
    import tempfile
    import time
    from pathlib import Path

    import numpy as np

    from clflow.fileio import atomic_dir, check_output_folder, content_digest, output_folder
    from clflow.fileio import digest as digests

    size = int(gb * 1e9) // files
    data = np.random.default_rng(0).integers(0, 255, size, dtype=np.uint8)
    entries = ("frame_*.bin",)

    def frames(folder: Path, sync: bool = False) -> None:
        for k in range(files):
            with open(folder / f"frame_{k:04d}.bin", "wb") as fh:
                data.tofile(fh)
                if sync:
                    fh.flush()
                    os.fsync(fh.fileno())

    def median(fn, setup=lambda: None) -> float:
        times = []
        for _ in range(repeat):
            setup()
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        return statistics.median(times)

    with tempfile.TemporaryDirectory(dir=where, prefix="clflow-bench-write-") as tmp:
        root = Path(tmp)
        plain = root / "plain"
        plain.mkdir()
        out = root / "out"
        with atomic_dir(out, entries) as new:
            frames(new)
        forget = digests._DIGESTS.clear  # a new process: nothing read yet
        results = {
            "bytes_s": median(lambda: frames(plain)),
            "bytes_fsync_s": median(lambda: frames(plain, sync=True)),
            "check_fingerprint_s": median(lambda: check_output_folder(out, entries), forget),
            "digests_s": median(lambda: [content_digest(p) for p in plain.iterdir()], forget),
        }

        def write_over() -> None:
            with atomic_dir(out, entries) as new:
                frames(new)

        results["atomic_dir_s"] = median(write_over, forget)
        copy = root / "copy"
        results["check_digest_s"] = median(
            lambda: check_output_folder(copy, entries),
            lambda: (shutil.rmtree(copy, ignore_errors=True), shutil.copytree(out, copy), forget()),
        )
        start = time.perf_counter()
        for _ in range(100):
            with output_folder(out):
                pass
        results["lock_s"] = (time.perf_counter() - start) / 100
    results["overhead_vs_fsync"] = results["atomic_dir_s"] / results["bytes_fsync_s"]
    click.echo(f"a result of {gb:g} GB in {files} files in {Path(where).resolve()}, median of {repeat}:")
    rows = [
        ("its bytes", "bytes_s"),
        ("its bytes, each file synced", "bytes_fsync_s"),
        ("atomic_dir over the earlier result", "atomic_dir_s"),
        ("  check of the earlier one, by fingerprint", "check_fingerprint_s"),
        ("  check by digest (a copied folder)", "check_digest_s"),
        ("  the digests (SHA-256)", "digests_s"),
        ("  the lock, taken and given back", "lock_s"),
    ]
    for label, key in rows:
        click.echo(f"  {label:<44}{results[key]:10.4f} s")
    click.echo(f"  atomic_dir / synced bytes: {results['overhead_vs_fsync']:.2f}x")
    return results
