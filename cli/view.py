"""``clflow view PATH``: a local web viewer of a 3DGS PLY or a simulation folder (extra ``view``)."""

import click


@click.command("view")
@click.argument("path", type=click.Path(path_type=str))
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to serve on; 0.0.0.0 lets other machines connect (given the printed address).")  # fmt: skip
@click.option("--port", type=click.IntRange(0, 65535), default=8080, show_default=True,
              help="Port to serve on (0: any free port).")  # fmt: skip
@click.option("--up", type=click.Choice(["+x", "-x", "+y", "-y", "+z", "-z"]), default="+y", show_default=True,
              help="A PLY file's up axis (a simulation folder knows its own).")  # fmt: skip
@click.pass_obj
def view(obj, path, host, port, up):
    """Show PATH in the browser: a 3DGS PLY file, or a simulation folder (`clflow simulate
    CONFIG`'s, or a results folder holding one) with a frame slider, play and the guidance
    camera. Drag the box's corner gizmos or type its min / max: its bounds are printed as
    the object.select.box YAML of a scene config (scene units). Open the address it prints:
    it carries this run's token, without which the viewer refuses every request. Ctrl-C stops."""
    import logging

    from clflow.view import Viewer, check_port, import_viser, load_scene

    if obj.verbosity < 1:  # a line per browser connection only with -v
        logging.getLogger("websockets").setLevel(logging.WARNING)

    import_viser()  # the extra and the port first, before reading a large file
    check_port(host, port)
    scene = load_scene(path, up)
    viewer = Viewer(scene, host, port, report=click.echo)
    frames = f", {scene.frame_count} frames" if scene.frame_count > 1 else ""
    try:  # from here on Ctrl-C is the way out, also while the line below is being written
        click.echo(
            f"viewing {scene.source} ({scene.rgbs.shape[0]:,} Gaussians{frames}) at {viewer.url()}; Ctrl-C stops",
            err=True,
        )
        viewer.serve_forever()
    except KeyboardInterrupt:
        viewer.close()
        raise KeyboardInterrupt("stopped (Ctrl-C)") from None  # one line and exit status 130, as every command
