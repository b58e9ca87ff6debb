"""The ``leap`` command line. Each command keeps its heavy imports inside its function so ``leap --help``
stays fast."""

from __future__ import annotations

import typer

app = typer.Typer(
    name="leap",
    help="LeAP Studio: open-vocabulary 3D point labeling from camera + LiDAR sequences.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)


def fail(message: str) -> typer.Exit:
    """Print a one-line error to stderr and return the exit to raise (``raise fail(...)``)."""
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code=2)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
