"""`pmem query similar`: find more like a cluster, an object or an image file (queries/
similar.py). Its options are the HTTP query's fields, but for `--image`, which names a PNG or
JPEG file here instead of carrying it in base64."""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import click

from percept_memory.cli import example, model_from_options, model_params
from percept_memory.memory.settings import Settings


@click.pass_obj
def _similar(settings: Settings, as_json: bool, image: Path | None, **given: Any) -> None:
    from percept_memory import answers
    from percept_memory.memory.store import MemoryStore
    from percept_memory.queries.similar import MAX_IMAGE_BYTES, Similarity, SimilarQuery

    if image is not None:
        if image.stat().st_size > MAX_IMAGE_BYTES:
            raise click.ClickException(f"{image} is over the limit of {MAX_IMAGE_BYTES} bytes")
        given["image"] = base64.b64encode(image.read_bytes()).decode()
    query = model_from_options(SimilarQuery, given)
    with MemoryStore.open(settings) as store:
        found = Similarity(store, settings).similar_to(query)
    if not found.items:
        raise click.ClickException(f"nothing else to compare with {found.start} "
                                   "(within the filters)")
    click.echo(answers.as_json(found) if as_json else answers.as_text(found))


def similar_command() -> click.Command:
    from percept_memory.queries.similar import SimilarQuery

    return click.Command(
        "similar", callback=_similar,
        params=[*(p for p in model_params(SimilarQuery) if p.name != "image"),
                click.Option(["--image"], type=click.Path(exists=True, dir_okay=False,
                                                          path_type=Path),
                             help="a PNG or JPEG crop to start from"),
                click.Option(["--json", "as_json"], is_flag=True,
                             help="print the answer as JSON (times as ISO 8601 and in ns)")],
        help="The observations that look most like a cluster, an object (by id or name: its "
             "latest observation) or an image, best first, with their similarity. Nothing "
             "found is an error.",
        epilog=example("pmem query similar --object ketchup --region counter_top_sink",
                       "pmem query similar --cluster 65e5a0c0e4b0a1b2c3d4e5f6 --k 5 --json",
                       "pmem query similar --image cup.png --descriptor crop-hog"))
