"""``clflow devices``: the OpenCL platforms and devices clflow can use."""

import click


@click.command()
@click.option("--json", "as_json", is_flag=True, help="Print a JSON list instead of a table.")
@click.pass_obj
def devices(obj, as_json: bool) -> None:
    """List OpenCL devices with the capabilities clflow uses.

    The device marked '*' is the one clflow selects (--device / CLFLOW_DEVICE / default).
    An NVIDIA, AMD or Intel OpenCL driver that is installed but has no ICD entry is used for
    the process and listed with the line that registers it for every program.
    """
    import dataclasses
    import json

    from clflow.runtime import get_device, list_devices
    from clflow.runtime.drivers import adopt_unregistered
    from clflow.runtime.plan import plan_for_type
    from clflow.runtime.program_cache import program_cache_dir

    folder = program_cache_dir()
    programs = None if folder is None else str(folder)  # None: $CLFLOW_PROGRAM_CACHE=off
    infos = list_devices()
    selected = get_device(obj.device_spec).info
    adoption = adopt_unregistered(get_device(obj.device_spec).kernel_cache_dir.parent)
    unregistered = [
        {"vendor": d.vendor, "path": str(d.path), "used": adoption.used, "register": d.how_to_register()}
        for d in adoption.drivers
    ]
    if as_json:
        rows = [
            dict(dataclasses.asdict(i), selected=(i == selected), kernel_plan=dataclasses.asdict(plan_for_type(i.type)))
            for i in infos
        ]
        caches = {"kernel_cache_dir": str(get_device(obj.device_spec).kernel_cache_dir), "program_cache_dir": programs}
        click.echo(json.dumps({"devices": rows, **caches, "unregistered_drivers": unregistered}, indent=2))
        return
    yes = {True: "yes", False: "no"}
    for info in infos:
        mark = "*" if info == selected else " "
        click.echo(f"{mark} {info.label}")
        click.echo(f"    type:               {info.type}")
        click.echo(f"    OpenCL:             {info.opencl_version}; {info.opencl_c_version}")
        click.echo(f"    fp64:               {yes[info.fp64]}")
        click.echo(f"    float atomics:      {yes[info.float_atomics]}")
        click.echo(f"    unified memory:     {yes[info.host_unified_memory]}")
        click.echo(f"    compute units:      {info.compute_units}")
        click.echo(f"    max work-group:     {info.max_work_group_size}")
        click.echo(f"    local memory:       {info.local_mem_size // 1024} KiB")
        click.echo(f"    global memory:      {info.global_mem_size / 2**30:.1f} GiB")
        click.echo(f"    kernel plan:        {plan_for_type(info.type).describe()}")
    click.echo(f"kernel cache dir: {get_device(obj.device_spec).kernel_cache_dir}")
    click.echo(f"program cache dir: {programs or 'off ($CLFLOW_PROGRAM_CACHE)'}")
    for d in unregistered:
        how = "used for this process" if d["used"] else "not used (CLFLOW_ADOPT_DRIVERS=0 or a read-only cache)"
        click.echo(
            f"note: the {d['vendor']} OpenCL driver {d['path']} has no ICD entry; {how}. "
            f"To register it for every program: {d['register']}"
        )
