"""``clflow query IMAGE``: decide the object's material type, density and initial parameters."""

from pathlib import Path

import click

from clflow_cli.options import InputFile, OutputPath, out_option, pixel_box_option

# The same names as clflow.query.BACKENDS (tests/query/test_cli.py checks); written out so
# that --help does not import numpy and OpenCV.
BACKEND_CHOICES = ("offline", "openai")


@click.command()
@click.argument("image", type=InputFile(path_type=Path))
@click.option("--prompt", default="", help="Text about the object or scene, sent with the image.")
@click.option("--name", "object_name", default="", metavar="TEXT",
              help="What the object is ('rubber duck'): the strongest hint for the offline backend.")  # fmt: skip
@pixel_box_option()
@click.option("--mask", type=InputFile(path_type=Path), default=None,
              help="Image of the same size whose nonzero pixels are the object.")  # fmt: skip
@click.option("--backend", type=click.Choice(BACKEND_CHOICES), default="offline", show_default=True,
              help="offline: the shipped knowledge base; openai: an OpenAI-compatible chat-completions server.")  # fmt: skip
@click.option("--llm-url", default=None, metavar="URL",
              help="Chat-completions endpoint or base URL (default $CLFLOW_LLM_URL, then $OPENAI_BASE_URL), "
              "e.g. http://localhost:11434/v1. The key is read from $CLFLOW_LLM_API_KEY or $OPENAI_API_KEY.")  # fmt: skip
@click.option("--model", default=None, metavar="NAME", help="Vision model name (default $CLFLOW_LLM_MODEL).")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=60.0, show_default=True,
              help="Seconds to wait for the connection and for each read.")  # fmt: skip
@click.option("--retries", type=click.IntRange(min=0), default=2, show_default=True,
              help="Retries after a connection failure, timeout or HTTP 408/429/5xx.")  # fmt: skip
@click.option("--image-format", type=click.Choice(["png", "jpeg"]), default="png", show_default=True,
              help="Encoding of the crop sent to the model.")  # fmt: skip
@out_option("output", "Result JSON (default: IMAGE's name + .material.json in the current folder).",
            type=OutputPath(file=True, path_type=Path))  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print the result record instead of a summary.")
def query(
    image, prompt, object_name, box, mask, backend, llm_url, model, timeout, retries, image_format, output, as_json
) -> None:
    """Decide the material of the object in IMAGE: type, density and initial parameters (SI).

    Writes a JSON record that the optimisation stage reads as its initial guess
    (clflow.query.load_query_result).
    """
    import json

    from clflow.errors import InputError
    from clflow.limits import check_output
    from clflow.query import ModelConfig, query_material

    output = output or Path(f"{image.stem}.material.json")
    check_output(output.parent)
    config = None
    if backend == "openai":
        config = ModelConfig.resolve(llm_url, model, timeout=timeout, retries=retries, image_format=image_format)
    result = query_material(
        image, prompt=prompt, object_name=object_name, box=box, mask=mask, backend=backend, model_config=config
    )
    if result.backend == "offline" and not result.confidence:  # a default entry is no answer: write nothing
        raise InputError(
            f"the offline backend cannot tell what {image.name} shows (no knowledge-base entry matches "
            f"{result.prompt!r} and it names no material type); name the object (--name 'rubber duck') or "
            f"ask a model (--backend openai)"
        )
    path = result.save(output)
    if as_json:
        click.echo(json.dumps(result.to_dict(), indent=2))
        return
    click.echo(summary(result))
    click.echo(f"wrote {path}")


def summary(result) -> str:
    """A readable multi-line summary of a QueryResult."""
    from clflow.materials import get_material

    mat = get_material(result.material)
    how = []
    if result.matched:
        how.append(f"knowledge-base entry {result.matched!r}")
    if result.confidence is not None:
        how.append(f"confidence {result.confidence:.2f}")
    lines = [
        f"object      {result.object or '(unknown)'}" + (f"  ({', '.join(how)})" if how else ""),
        f"material    {mat.name}: {mat.model}",
        f"density     {result.density:g} kg/m^3",
    ]
    width = max(len(f"{p.name} ({p.symbol})") for p in mat.params)
    for i, p in enumerate(mat.params):
        label = "parameters" if i == 0 else ""
        unit = "" if p.unit == "1" else f" {p.unit}"
        lines.append(f"{label:<11} {f'{p.name} ({p.symbol})':<{width}}  {result.parameters[p.name]:g}{unit}")
    backend = result.backend
    if result.model:
        structured = {True: ", json_schema", False: ", JSON asked in the prompt"}.get(result.structured_output, "")
        backend += f" (model {result.model}{structured})"
    lines.append(f"backend     {backend}")
    lines += [f"warning: {w}" for w in result.warnings]
    return "\n".join(lines)
