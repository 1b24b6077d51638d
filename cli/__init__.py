"""clflow's click command-line interface (installed as ``clflow_cli``).

The root group lives in :mod:`clflow_cli.main`; every subcommand is its own module in this
package and is imported only when it runs (or when ``--help`` lists it), so ``clflow --help``
stays instant. Third-party packages add subcommands through the ``clflow.commands``
entry-point group.
"""
