"""``clflow bench query``: speed of the material query's local work (no network)."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option


@bench_command("query")
@count_option('--repeat', default=20, help="Timed repetitions of each measurement (the median is reported).")  # fmt: skip
def query(repeat: int) -> dict:
    """Offline knowledge-base lookups and image preparation for the model backend.

    Lookups: the median time of one offline query over texts of 2-12 words, with typos,
    file names and texts that match nothing; "first" when the knowledge base meets the
    words for the first time, "repeat" when it has seen them (it caches word similarity).
    Image: crop a 1920x1080 photo to a box,
    downscale to 1024 px and encode as base64 PNG / JPEG (what the openai backend sends).
    """
    import tempfile
    from importlib import resources
    from pathlib import Path

    import cv2
    import numpy as np

    from clflow.benchmark import measure
    from clflow.query import crop_object, load_knowledge_base

    def median_ms(fn, setup=lambda: None) -> float:
        return 1e3 * measure(fn, repeat, setup=setup).median_wall

    results = {}

    texts = [
        "rubber duck",
        "a jar of strawberry jam on a wooden kitchen table next to a spoon",
        "IMG_0042-RubberDucks",
        "alumnium foil",
        "xyzzy qwerty",
        "a glass of milk",
        "a red carnation in a vase on the window sill",
        "sandcastle on the beach",
    ]
    kb_file = resources.files("clflow") / "data" / "materials_kb.json"
    kb = load_knowledge_base(kb_file)
    for label, setup in (("first", lambda: load_knowledge_base(kb_file)), ("repeat", lambda: kb)):
        ms = median_ms(lambda base: [base.match(prompt=t) for t in texts], setup) / len(texts)
        results[f"lookup_{label}_ms"] = ms
        click.echo(
            f"offline lookup {label:<6}{ms:8.3f} ms/query   ({len(kb.entries)} entries, "
            f"{sum(len(e.aliases) for e in kb.entries)} aliases)"
        )

    rng = np.random.default_rng(0)
    photo = cv2.GaussianBlur(rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8), (0, 0), 3)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "photo.png"
        cv2.imwrite(str(path), photo)
        crop = crop_object(path, box=(400, 100, 1800, 1000))
        for fmt in ("png", "jpeg"):
            ms = results[f"encode_{fmt}_ms"] = median_ms(lambda _: crop.data_url(fmt))
            size = len(crop.data_url(fmt)) / 1024
            click.echo(
                f"image {fmt:<4} encode   {ms:8.3f} ms         (1400x900 crop -> 1024 px, {size:.0f} KiB base64)"
            )
        ms = results["read_crop_ms"] = median_ms(lambda _: crop_object(path, box=(400, 100, 1800, 1000)))
        click.echo(f"image read + crop   {ms:8.3f} ms         (1920x1080 PNG)")
    return results
