"""The ``heliojax`` command: a thin dispatcher over the library.

Every subcommand accepts ``--config FILE.toml``: the table named after the
subcommand (e.g. ``[calibrate]``) supplies option defaults (keys are the long
option names with ``-`` or ``_``); flags on the command line override them.
float64 is enabled for every command (calibration and geodesy need it).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tomllib
from pathlib import Path

from .._errors import ConfigError, HeliojaxError
from .._version import __version__

# subcommand -> module (each has add_parser(subparsers) and run(args) -> int)
SUBCOMMANDS = {
    "inspect": "heliojax.cli._inspect",
    "calibrate": "heliojax.cli._calibrate",
    "discover": "heliojax.cli._discover",
    "fetch": "heliojax.cli._fetch",
    "accept": "heliojax.cli._accept",
    "trace": "heliojax.cli._trace",
    "reconstruct": "heliojax.cli._reconstruct",
}


def _available():
    for name, module in SUBCOMMANDS.items():
        try:
            yield name, importlib.import_module(module)
        except ModuleNotFoundError as e:  # a subcommand whose module is not part of this build
            if e.name != module:
                raise


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Option help with its default (unless the help names it or there is none to
    name: flags, unset options); descriptions and example epilogs as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "default" in text
            or default is None
            or default is argparse.SUPPRESS
            or isinstance(default, bool)
            or not (action.option_strings or action.nargs in ("?", "*"))
        ):
            return text
        shown = ",".join(map(str, default)) if isinstance(default, list | tuple) else "%(default)s"
        return f"{text} (default: {shown})"


def build_parser() -> tuple[argparse.ArgumentParser, dict]:
    parser = argparse.ArgumentParser(
        prog="heliojax",
        formatter_class=_HelpFormatter,
        epilog="examples:\n  heliojax calibrate --plot out/calibration.png\n  heliojax inspect ../shared/data/paint\n"
        "  heliojax COMMAND --help",
        description="heliojax: a JAX digital twin of a heliostat field (PAINT data, Stone calibration).",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = {}
    for name, module in _available():
        module.add_parser(sub)
        modules[name] = module
        sp = sub.choices[name]
        sp.formatter_class = _HelpFormatter
        sp.epilog = module.EXAMPLES
        sp.add_argument("--config", type=Path, metavar="FILE", help=f"TOML file with option defaults (table [{name}])")
    return parser, modules


def _apply_config(subparser: argparse.ArgumentParser, command: str, path: Path) -> None:
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config: {e}") from e
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: malformed TOML: {e}") from e
    table = doc.get(command, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [{command}] must be a table")
    known = {a.dest: a for a in subparser._actions}
    defaults = {}
    for key, value in table.items():
        dest = key.replace("-", "_")
        if dest not in known or dest in ("help", "config"):
            raise ConfigError(f"{path}: [{command}] unknown option {key!r}")
        action = known[dest]
        if action.type is not None and isinstance(value, str) and not isinstance(action.type, type):
            value = action.type(value)  # pyright: ignore[reportCallIssue]
        elif action.type in (Path,) and isinstance(value, str):
            value = Path(value)
        defaults[dest] = value
    subparser.set_defaults(**defaults)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser, modules = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 2
    import jax  # after parsing: --help and --version stay fast

    jax.config.update("jax_enable_x64", True)
    try:
        if getattr(args, "config", None) is not None:
            sp = parser._subparsers._group_actions[0].choices[args.command]  # pyright: ignore[reportOptionalSubscript, reportOptionalMemberAccess, reportIndexIssue]
            _apply_config(sp, args.command, args.config)
            args = parser.parse_args(argv)
        return int(modules[args.command].run(args) or 0)
    except HeliojaxError as e:
        print(f"heliojax {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
