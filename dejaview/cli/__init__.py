"""The ``dejaview`` command line.

Subcommands live in their own modules and are imported only when used, so
``dejaview --help`` stays fast. Each module exposes one click command named
``command``.
"""

from __future__ import annotations

import importlib
import sys

import click

from dejaview import __version__
from dejaview.errors import DejaViewError

# name -> module holding a click command called ``command``
SUBCOMMANDS = {
    "validate": "dejaview.cli.validate",
    "pack": "dejaview.cli.pack",
    "simulate": "dejaview.cli.simulate",
    "solve": "dejaview.cli.solve",
    "identify": "dejaview.cli.identify",
    "train": "dejaview.cli.train",
    "heatmap": "dejaview.cli.heatmap",
    "serve": "dejaview.cli.serve",
    "client": "dejaview.cli.client",
    "bench": "dejaview.cli.bench",
    "export-mjcf": "dejaview.cli.export_mjcf",
    "import-mjcf": "dejaview.cli.import_mjcf",
}


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def list_commands(self, ctx):
        return [name for name in SUBCOMMANDS if self._available(name)]

    def get_command(self, ctx, name):
        if name not in SUBCOMMANDS or not self._available(name):
            return None
        return importlib.import_module(SUBCOMMANDS[name]).command

    @staticmethod
    def _available(name: str) -> bool:
        return importlib.util.find_spec(SUBCOMMANDS[name]) is not None


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="dejaview")
def cli():
    """DejaView: infer the past of a rigid object from where it ended up."""


def main(argv=None):
    """Console entry point: runs the CLI and turns DejaView errors into one line."""
    try:
        rv = cli.main(args=argv, prog_name="dejaview", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.exceptions.NoArgsIsHelpError as exc:
        exc.show()  # a bare ``dejaview``: the help text, not an error line
        sys.exit(exc.exit_code)
    except click.UsageError as exc:
        # one line naming the problem (scene-format spec, "Command line"); click would add
        # the usage and a help hint
        click.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except DejaViewError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        sys.exit(130)
    # standalone_mode=False hands back ctx.exit(n) codes instead of exiting
    sys.exit(rv if isinstance(rv, int) else 0)
