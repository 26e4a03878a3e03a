"""The `socnav` command line: train, evaluate, animate, calibrate, convert, run experiments, report, tune, demo.

Every command validates its options up front and reports bad input as one clear line, never a traceback. One module
per group of commands (`train`, `evaluate`, `deploy`, `demo`, `experiments`, `ros2`), the options they share declared
once (`options`), their shared checks and loaders (`common`), and the heavier steps some commands run
(`workflows`: the demo, animations, tuning), loaded only inside the commands so that `socnav --help` stays fast.
"""

from __future__ import annotations

import signal

import typer
from rich.markup import escape

from socnav._console import console
from socnav.cli import demo, deploy, evaluate, experiments, ros2, train
from socnav.config import ConfigError

__all__ = ["app", "main"]

# Plain click help: typer's rich help panels label every flag (and --help itself) with a `<bool>` type.
app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__.splitlines()[0], rich_markup_mode=None)


def _version(value: bool) -> None:
    if value:
        from socnav import __version__

        console.print(f"socnav {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="print the version and exit"),
) -> None:
    """Uncertainty-aware social robot navigation: simulate, train, evaluate, calibrate, run experiments."""


# The commands in the order `socnav --help` lists them, each from the module of its group.
for command in (train.train, evaluate.evaluate, evaluate.animate, deploy.calibrate, deploy.convert, demo.demo,
                deploy.export, train.plot):
    app.command()(command)
experiments.register(app)  # socnav run / report / tune
app.add_typer(ros2.app, name="ros2")  # socnav ros2 navigator / sim (imports no rclpy: each command loads it)


def _sigterm_as_interrupt(signum: int, frame: object) -> None:
    """SIGTERM's handler: the first Ctrl-C. A process whose SIGINT is ignored (a background job of a non-interactive
    shell starts so) would ignore the raised SIGINT too, and SIGTERM would no longer stop it: the interrupt is then
    raised here, and the command's KeyboardInterrupt handling runs."""
    if signal.getsignal(signal.SIGINT) in (signal.SIG_IGN, signal.SIG_DFL, None):
        raise KeyboardInterrupt
    signal.raise_signal(signal.SIGINT)


def _terminate_as_interrupt() -> None:
    """SIGTERM does what the first Ctrl-C does (a service manager, `kill`, a job scheduler send it): the command's own
    SIGINT handling runs -- `train` saves a checkpoint, `evaluate` writes its finished episodes, `run` stops its units
    -- instead of the process dying with its work unsaved. The ROS 2 nodes install their own handlers for both."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    signal.signal(signal.SIGTERM, _sigterm_as_interrupt)


def main() -> None:
    """Entry point of the `socnav` command and of `python -m socnav` (the usage line names `socnav`).

    A configuration error found only when a world is built (e.g. walls that cover every start of a scenario, found
    when episodes are drawn) is one line, as the errors found when the options are read; anything else keeps its
    traceback. SIGTERM is handled as the first Ctrl-C (`_terminate_as_interrupt`)."""
    _terminate_as_interrupt()
    try:
        app(prog_name="socnav")  # exits (SystemExit) unless a command raised: typer re-raises it
    except ConfigError as exc:
        console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False)
        raise SystemExit(2) from None

