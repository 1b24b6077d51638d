from clflow_cli.main import cli

cli(prog_name="clflow")
