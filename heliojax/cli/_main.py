"""The ``heliojax`` command: a thin dispatcher over the library.

Every subcommand accepts ``--config FILE.toml``: the table named after the
subcommand (e.g. ``[calibrate]``) supplies option defaults (keys are the long
option names with ``-`` or ``_``); flags on the command line override them.
float64 is enabled for every command (calibration and geodesy need it), and
XLA's CPU backend compiles with its older fusion emitters unless ``XLA_FLAGS``
says otherwise (2-3x faster compiles for ~20 % slower runs: see
``heliojax._xla_flags``).
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import importlib
import os
import re
import signal
import sys
import threading
import typing
from collections.abc import Callable, Iterable
from pathlib import Path

from .._errors import ConfigError, HeliojaxError, one_line
from .._version import __version__
from .._xla_flags import with_fast_cpu_compilation
from ._common import (
    check_input_paths,
    check_output_paths,
    configure_logging,
    note_interrupt,
    path_type,
    raise_if_interrupted,
    remember_programs,
)

# subcommand -> module (each has add_parser(subparsers) and run(args) -> int)
SUBCOMMANDS = {
    "inspect": "heliojax.cli._inspect",
    "calibrate": "heliojax.cli._calibrate",
    "aim": "heliojax.cli._aim",
    "plan": "heliojax.cli._plan",
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


class _Parser(argparse.ArgumentParser):
    """Usage errors in two lines: the error naming the flag, and where to find help;
    :attr:`options` (dest -> action) holds every option added, and :attr:`exclusive`
    the dests of each mutually exclusive group, for configs to be read as the command
    line would be."""

    def __init__(self, *args: typing.Any, **kwargs: typing.Any) -> None:
        self.options: dict[str, argparse.Action] = {}
        self.exclusive: list[list[str]] = []
        super().__init__(*args, **kwargs)

    def add_argument(self, *args: typing.Any, **kwargs: typing.Any) -> argparse.Action:
        action = super().add_argument(*args, **kwargs)
        self.options[action.dest] = action
        return action

    def add_mutually_exclusive_group(self, **kwargs: typing.Any) -> typing.Any:
        members: list[str] = []
        self.exclusive.append(members)
        return _RecordedGroup(super().add_mutually_exclusive_group(**kwargs), self.options, members)

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message)}\nsee '{self.prog} --help'\n")

    def parse_known_args(self, args=None, namespace=None):  # pyright: ignore[reportIncompatibleMethodOverride]
        # argparse drops a value '--' (``--out=--``) and sets the option to [] without its
        # type: a TypeError deep in a command, or ``--seed=--`` run with no seed
        for arg in list(args if args is not None else sys.argv[1:]):
            if arg == "--":  # the end of the options: what follows is no option
                break
            if arg.startswith("-") and arg.endswith("=--"):
                self.error(f"argument {arg.split('=', 1)[0]}: '--' is not a value")
        return super().parse_known_args(args, namespace)


class _RecordedGroup:
    """A mutually exclusive group whose options are recorded in its parser's ``options``
    and, by dest, in ``members`` (one entry of the parser's ``exclusive``)."""

    def __init__(self, group: typing.Any, options: dict[str, argparse.Action], members: list[str]) -> None:
        self.group, self.options, self.members = group, options, members

    def add_argument(self, *args: typing.Any, **kwargs: typing.Any) -> argparse.Action:
        action = self.group.add_argument(*args, **kwargs)
        self.options[action.dest] = action
        self.members.append(action.dest)
        return action


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


def build_parser() -> tuple[argparse.ArgumentParser, dict, dict[str, argparse.ArgumentParser]]:
    """The ``heliojax`` parser, the subcommand modules and the subcommand parsers
    (both keyed by subcommand name)."""
    parser = _Parser(
        prog="heliojax",
        formatter_class=_HelpFormatter,
        epilog="examples:\n  heliojax calibrate --plot out/calibration.png\n  heliojax inspect ../shared/data/paint\n"
        "  heliojax COMMAND --help",
        description="heliojax: a JAX digital twin of a heliostat field (PAINT data, Stone calibration).",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules, subparsers = {}, {}
    for name, module in _available():
        module.add_parser(sub)
        modules[name] = module
        sp = subparsers[name] = sub.choices[name]
        sp.formatter_class = _HelpFormatter
        sp.epilog = module.EXAMPLES
        sp.add_argument(
            "--config", type=path_type, metavar="FILE", help=f"TOML file with option defaults (table [{name}])"
        )
    return parser, modules, subparsers


def _apply_config(
    subparser: argparse.ArgumentParser,
    command: str,
    path: Path,
    commands: Iterable[str],
    given: argparse.Namespace | None = None,
    partners: dict[str, tuple[str, ...]] | None = None,
    outputs: Iterable[str] = (),
) -> None:
    """Option defaults from the ``[command]`` table of ``path``. ``given``: the command
    line parsed alone; an option of a mutually exclusive group given there drops the
    config's values of the group's other options (and of their ``partners``, e.g.
    ``--start``'s ``--end``): the command line wins, as with any other option.
    ``outputs``: the command's output options, whose values keep the command line's
    rules (:func:`~heliojax.cli._common.output_path_problem`), named by their key."""
    import tomllib  # only with --config

    from ._common import check_input_file, output_path_problem

    check_input_file("--config", path)
    try:
        with open(path, "rb") as f:
            text = f.read()
        doc = tomllib.loads(text.decode().removeprefix("\ufeff"))  # a byte order mark: saved by Notepad
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config: {e}") from e
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: malformed TOML: {e}") from e
    except RecursionError:  # tomllib recurses once per level of nested arrays or tables
        raise ConfigError(f"{path}: malformed TOML: nested too deep") from None
    unknown_tables = sorted(set(doc) - set(commands))
    if unknown_tables:
        hint = _unknown_name_hint(unknown_tables[0], commands) if len(unknown_tables) == 1 else ""
        raise ConfigError(
            f"{path}: unknown table(s) [{', '.join(_quoted(t) for t in unknown_tables)}]; tables are named after "
            f"commands: {sorted(commands)}{hint}"
        )
    table = doc.get(command, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [{command}] must be a table")
    known = subparser.options if isinstance(subparser, _Parser) else {}
    defaults, keys = {}, {}
    finer = finer_date_times(text.decode(errors="replace"))
    for key, value in table.items():
        dest = key.replace("-", "_")
        if dest not in known or dest in ("help", "config"):
            keys_allowed = [d for d, a in known.items() if d not in ("help", "config") and not a.required]
            flags = [d for d in keys_allowed if known[d].nargs == 0]
            hint = _unknown_name_hint(dest, keys_allowed, flags, value)
            raise ConfigError(f"{path}: [{command}] unknown option {_quoted(key)}{hint}")
        if dest in keys:  # max_steps and "max-steps": one would silently win
            raise ConfigError(f"{path}: [{command}] {keys[dest]!r} and {key!r} are the same option: give it once")
        if known[dest].required:  # argparse asks the command line for it before the config is read
            raise ConfigError(f"{path}: [{command}] {key}: required on the command line, where it must be given")
        keys[dest] = key
        where = f"{path}: [{command}] {key}"
        _check_sub_microseconds(value, where, finer)
        defaults[dest] = _config_value(known[dest], value, where)
        if dest in outputs and defaults[dest] is not None:
            problem = output_path_problem(str(defaults[dest]))
            if problem is not None:
                raise ConfigError(f"{where}: {str(defaults[dest])!r}: {problem}")
    for members in subparser.exclusive if isinstance(subparser, _Parser) else ():
        set_here = [keys[d] for d in members if d in keys]
        if len(set_here) > 1:
            raise ConfigError(f"{path}: [{command}] {' and '.join(set_here)} exclude each other: give one")
        on_line = [d for d in members if getattr(given, d, None) is not None]
        for dest in members if on_line else ():
            if dest not in on_line:
                for dropped in (dest, *(partners or {}).get(dest, ())):
                    defaults.pop(dropped, None)
    # where each value the command line leaves to the config comes from (for its messages:
    # heliojax.cli._common.option_label)
    origin = {d: (f"{path}: [{command}] {keys[d]}", v) for d, v in defaults.items()}
    subparser.set_defaults(**defaults, config_origin=origin)


def _quoted(name: str, limit: int = 60) -> str:
    """``name`` (a config file's key or table, any string) as an error message quotes it:
    its ``repr``, cut to ``limit`` characters with ``...`` (a 5,000-character key had
    made a 5,000-character message)."""
    text = repr(name)
    return text if len(text) <= limit else text[: limit - 4] + "...'"


def _unknown_name_hint(name: str, known: Iterable[str], flags: Iterable[str] = (), value: object = None) -> str:
    """What to write instead of an unknown config key or table ``name`` (``-`` read as
    ``_``; ``value``: the key's), to follow its error message: for ``no_X`` where ``X``
    is one of ``flags`` (on/off options, read from ``true`` / ``false``), ``use `X =
    false``` (``true`` for ``no_X = false``), and for ``X`` where the flag is ``no_X``
    (``discover``'s ``no_robust``), ``use `no_X = true``` (``false`` for ``X = true``);
    otherwise the closest of ``known`` (:func:`difflib.get_close_matches`), if one is
    close; else ``""``. One rule for every command's ``--config``."""
    import difflib

    dest = name.replace("-", "_")
    flags = set(flags)
    if dest.startswith("no_") and dest[3:] in flags:
        return f"; use `{dest[3:]} = {'true' if value is False else 'false'}`"
    if f"no_{dest}" in flags:
        return f"; use `no_{dest} = {'false' if value is True else 'true'}`"
    close = difflib.get_close_matches(dest, sorted(known), n=1)
    return f"; did you mean `{close[0]}`?" if close else ""


_FINER_THAN_MICROSECONDS = re.compile(r"(\d{4}-\d{2}-\d{2}[Tt ]\d{2}:\d{2}:\d{2})\.\d{7,}", re.ASCII)
"""A TOML date-time written with more than 6 fractional-second digits (group 1: its
date and time to the second)."""


def _bare_toml(text: str) -> str:
    """``text`` with its comments and string literals (basic, literal, multi-line)
    blanked out: what is left are keys, tables and bare values (numbers, booleans,
    dates). The file has parsed already, so every literal is closed."""
    out: list[str] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c == "#":
            j = text.find("\n", i)
            i = n if j < 0 else j
            continue
        if c in "\"'":
            quote = c * 3 if text.startswith(c * 3, i) else c
            j = i + len(quote)
            while j < n and not text.startswith(quote, j):
                j += 2 if (c == '"' and text[j] == "\\") else 1
            j += len(quote)
            while quote != c and j < n and text[j] == c:  # up to two quotes close a multi-line string too
                j += 1
            out.append(" ")
            i = j
            continue
        out.append(c)
        i += 1
    return "".join(out)


def finer_date_times(text: str) -> set[str]:
    """Date and time to the second (``YYYY-MM-DDTHH:MM:SS``) of the TOML date-times in
    ``text`` written with more than 6 fractional-second digits, comments and strings
    left out (a comment with such a time says nothing about a key's value)."""
    return {m[1].upper().replace(" ", "T") for m in _FINER_THAN_MICROSECONDS.finditer(_bare_toml(text))}


def _check_sub_microseconds(value: object, where: str, finer: set[str]) -> None:
    """A TOML date-time (or an array of them) of a config key that the file wrote with
    more than 6 fractional digits (``finer``: their date and time to the second, from
    :data:`_FINER_THAN_MICROSECONDS`): tomllib keeps microseconds and drops the rest
    without a word, where the command line refuses the 7th digit
    (:func:`~heliojax.cli._common.is_iso_date_time`)."""
    for item in value if isinstance(value, list) else [value]:
        if isinstance(item, dt.datetime) and item.strftime("%Y-%m-%dT%H:%M:%S") in finer:
            raise ConfigError(
                f"{where}: a date-time with more than 6 fractional-second digits (read, the rest would be "
                "dropped without a word); give at most 6 (microseconds)"
            )


def _config_value(action: argparse.Action, value: object, where: str) -> object:
    """A config value converted as the command line would convert it, or ConfigError."""
    if action.nargs == 0:  # flags: store_true / store_false
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value  # the option's own value: `robust = false` is --no-robust
    if action.nargs in ("+", "*"):  # a list option: an array of values (one string is a list of one)
        items = value if isinstance(value, list) else [value]
        if not items and action.nargs == "+":
            raise ConfigError(f"{where}: expected at least one value, got an empty array")
        return [_config_value(_one_of(action), v, where) for v in items]
    kind = action.type
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        value = float(value)
    elif kind is None or kind is str or kind is Path or kind is path_type:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        if kind is path_type:
            try:
                value = path_type(value)
            except argparse.ArgumentTypeError as e:
                raise ConfigError(f"{where}: {e}") from e
        value = Path(value) if kind is Path else value
    else:  # the option's own parser (ranges, lists, dates): strings, and numbers where it takes them
        if isinstance(value, dt.date):  # dt.datetime too
            value = value.isoformat()  # a TOML date or date-time, read as its ISO text would be
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise ConfigError(f"{where}: expected a string or a number, got {value!r}")
        numeric = {"integer": "an integer", "number": "a number"}.get(getattr(kind, "__name__", ""))
        if numeric is not None and isinstance(value, str):  # TOML has numbers (and inf, nan): "10" is a typo
            raise ConfigError(f"{where}: expected {numeric}, got the string {value!r} (write it without quotes)")
        if numeric == "an integer" and isinstance(value, float):  # as --max-steps 1e3 is refused
            raise ConfigError(f"{where}: expected an integer, got the float {value!r}")
        try:
            value = kind(value)  # pyright: ignore[reportCallIssue, reportArgumentType]
        except (ValueError, TypeError, AttributeError, argparse.ArgumentTypeError) as e:
            if not isinstance(value, str) and isinstance(e, TypeError | AttributeError):  # a parser of strings only
                raise ConfigError(f"{where}: expected a string, got {value!r}") from None
            raise ConfigError(f"{where}: {e}") from e
    if action.choices is not None and value not in action.choices:
        raise ConfigError(f"{where}: {value!r} is not one of {list(action.choices)}")
    return value


def _one_of(action: argparse.Action) -> argparse.Action:
    """``action`` for one value of a list option (its type and choices, no ``nargs``)."""
    return argparse.Action(action.option_strings, action.dest, type=action.type, choices=action.choices)  # pyright: ignore[reportArgumentType]


def _private_matplotlib_folder() -> str | None:
    """A temporary folder made ``$MPLCONFIGDIR`` when matplotlib's own folders (config
    and cache: ``$XDG_CONFIG_HOME/matplotlib``, ``$XDG_CACHE_HOME/matplotlib``, under
    ``$HOME`` by default) cannot be made or written, else None (``$MPLCONFIGDIR`` set, or
    usable folders). With an unwritable ``$HOME`` matplotlib printed two lines of
    warnings on its import and made a ``/tmp/matplotlib-*`` folder of its own, which no
    run removed (its removal at exit is skipped by :func:`main`'s quick exit); this one is
    removed when the command ends (:func:`main`)."""
    import tempfile

    if os.environ.get("MPLCONFIGDIR", "").strip() or not sys.platform.startswith(("linux", "freebsd")):
        return None
    try:
        for variable, default in (("XDG_CONFIG_HOME", ".config"), ("XDG_CACHE_HOME", ".cache")):
            folder = Path(os.environ.get(variable) or Path.home() / default, "matplotlib").resolve()
            folder.mkdir(parents=True, exist_ok=True)  # matplotlib's rule (its _get_config_or_cache_dir)
            if not (os.access(folder, os.W_OK) and folder.is_dir()):
                raise PermissionError(folder)
        return None
    except (OSError, RuntimeError):  # RuntimeError: no home folder
        pass
    try:
        folder = tempfile.mkdtemp(prefix="heliojax-matplotlib-")
    except OSError:  # no temporary folder either: matplotlib says so itself
        return None
    os.environ["MPLCONFIGDIR"] = folder
    return folder


class _NamedStdout:
    """``sys.stdout`` whose write errors (a full disk, ``> /dev/full``) name it: an
    OSError of a write carries no file name, and the error line would name nothing. A
    character its encoding lacks (an ASCII stdout of ``PYTHONUTF8=0 LC_ALL=C``: the
    'ü' of Jülich in ``plan --help`` ended in a UnicodeEncodeError traceback, as did a
    non-UTF-8 file name in a table) is written escaped, as standard error writes it."""

    def __init__(self, stream: typing.Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            try:
                return self._stream.write(text)
            except UnicodeEncodeError:
                encoding = getattr(self._stream, "encoding", None) or "ascii"
                return self._stream.write(text.encode(encoding, "backslashreplace").decode(encoding))
        except OSError as e:
            raise OSError(e.errno, e.strerror or str(e), "standard output") from None

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as e:
            raise OSError(e.errno, e.strerror or str(e), "standard output") from None

    def __getattr__(self, name: str) -> typing.Any:
        return getattr(self._stream, name)


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (``signum``), raised in the main thread like Ctrl-C's
    KeyboardInterrupt so that every ``finally`` and cleanup runs (temporary files
    removed, partial outputs not renamed)."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def word(self) -> str:
        """How the command's last line says it ended: ``terminated`` or ``hung up``."""
        return "hung up" if self.signum == _SIGHUP else "terminated"


_SIGHUP = getattr(signal, "SIGHUP", None)
"""The hangup signal (a closed terminal or ssh session; None where there is none)."""


def _interrupt(signum: int, frame: object) -> typing.NoReturn:
    """Ctrl-C (SIGINT), SIGTERM and SIGHUP: remembered (:func:`note_interrupt`), then raised."""
    interrupt = Terminated(signum) if signum in (signal.SIGTERM, _SIGHUP) else KeyboardInterrupt()
    note_interrupt(interrupt)
    raise interrupt


def _catch_hangup() -> typing.Any:
    """Handle SIGHUP as SIGTERM (:func:`_interrupt`): a closed terminal or ssh session
    killed the command where it stood, leaving the temporaries of the outputs it was
    writing. Not where it is ignored (``nohup``: the command is meant to carry on) or
    does not exist. Returns the previous handler to restore, or None."""
    if _SIGHUP is None or signal.getsignal(_SIGHUP) == signal.SIG_IGN:
        return None
    return signal.signal(_SIGHUP, _interrupt)


def _quiet_unraisable(previous: Callable[[typing.Any], object], unraisable: typing.Any) -> object:
    """``sys.unraisablehook`` (with ``previous`` bound by :func:`functools.partial`) that
    keeps an interrupt raised where Python swallows exceptions (a garbage-collector
    callback) off standard error: it was remembered and stops the command at its next
    check (:func:`raise_if_interrupted`)."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        return None
    return previous(unraisable)


def main(argv: list[str] | None = None) -> int:
    """``heliojax COMMAND ...``; the exit status: 0, 2 (bad input, a usage error; fetch:
    some files failed or a heliostat asked for is not in the catalogue), 130 (Ctrl-C),
    143 (SIGTERM) or 129 (SIGHUP): interrupted, a line without a traceback, and no
    output half written.

    Run as the ``heliojax`` program (``argv`` None, in the main thread), the process
    ends here once standard output and error are flushed (:func:`os._exit`): every
    output is written, closed and renamed by then, and the interpreter's teardown
    (JAX's exit handlers freeing its compiled programs, ~0.4 s on 2 cores) would only
    make the user wait, with a Ctrl-C in it answered by an exit handler's traceback."""
    from_console = argv is None  # the `heliojax` program itself, not a caller in Python
    argv = sys.argv[1:] if argv is None else list(argv)
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupt) if in_main_thread else None
    previous_hup = _catch_hangup() if in_main_thread else None
    previous_int = signal.signal(signal.SIGINT, _interrupt) if in_main_thread else None
    previous_hook = sys.unraisablehook
    sys.unraisablehook = functools.partial(_quiet_unraisable, previous_hook)
    note_interrupt(None)
    stdout, stderr = sys.stdout, sys.stderr
    if stdout is not None:  # None: started with standard output closed (`>&-`); print() writes nothing
        sys.stdout = _NamedStdout(stdout)
    if stderr is None:  # started with standard error closed (`2>&-`): progress bars wrote to None and failed
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115 (closed in the finally below)
    command = next((a for a in argv if a in SUBCOMMANDS), "")
    matplotlib_folder = _private_matplotlib_folder() if command else None
    try:
        code = _main(argv)
        raise_if_interrupted()  # received but swallowed where it was raised: the command stops here
        if from_console and in_main_thread and sys.stdout is not None:
            sys.stdout.flush()  # `--version > /dev/full`: named below, not at exit
    except KeyboardInterrupt as e:
        print(
            f"heliojax{' ' + command if command else ''}: {e.word if isinstance(e, Terminated) else 'interrupted'}: "
            "outputs not finished were not written",
            file=sys.stderr,
        )
        code = 128 + (e.signum if isinstance(e, Terminated) else signal.SIGINT)  # 143 SIGTERM, 129 SIGHUP, 130
    except OSError as e:  # standard output full or closed, outside a command's own handler
        code = _os_error(command, e)
    finally:
        sys.stdout = stdout
        if stderr is None:
            sys.stderr.close()
            sys.stderr = stderr
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if previous_hup is not None and _SIGHUP is not None:
            signal.signal(_SIGHUP, previous_hup)
        if from_console and in_main_thread:
            # the command has ended (its outputs written or not, and said so): a Ctrl-C
            # from here on would exit 130 without a word
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        elif previous_int is not None:
            signal.signal(signal.SIGINT, previous_int)
        sys.unraisablehook = previous_hook
        note_interrupt(None)
        if matplotlib_folder is not None:
            import shutil

            shutil.rmtree(matplotlib_folder, ignore_errors=True)
            os.environ.pop("MPLCONFIGDIR", None)
    if from_console and in_main_thread:
        for stream in (sys.stderr, sys.stdout):
            try:
                if stream is not None:
                    stream.flush()
            except (OSError, ValueError):  # said above where it could be said; nothing more to do
                pass
        os._exit(code)
    return code


def _config_keys_named(message: str, args: argparse.Namespace) -> str:
    """``message`` whose subject, the flag it starts with, is named by the ``--config``
    file and key its value came from (not the command line;
    :func:`~heliojax.cli._common.option_label`): the user wrote ``val = 1_000``, not
    ``--val 1000``. Flags named further on are references and stay as they are."""
    from ._common import option_label

    for dest in getattr(args, "config_origin", {}):
        flag = "--" + dest.replace("_", "-")
        label = option_label(args, dest, flag)
        if label != flag and re.match(rf"{re.escape(flag)}(?![\w-])", message):
            return label + message[len(flag) :]
    return message


def _os_error(command: str, e: OSError) -> int:
    """The exit status and one line for ``e``, a file that vanished or turned unwritable
    while running (standard output too: ``> /dev/full``; ``| head -1`` ends quietly)."""
    if isinstance(e, BrokenPipeError) and e.filename == "standard output":
        _silence_stdout()  # `heliojax inspect | head -1`: the reader had enough, as with any Unix tool
        return 141  # 128 + SIGPIPE
    where = f"{e.filename}: " if e.filename else ""
    name = f"heliojax {command}" if command else "heliojax"
    print(f"{name}: error: {one_line(f'{where}{e.strerror or e}')}", file=sys.stderr)
    return 2


def _silence_stdout() -> None:
    """Point standard output at /dev/null: the flush at exit would fail on the closed pipe again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.__stdout__.fileno() if sys.__stdout__ is not None else 1)
    except (OSError, ValueError):  # no file descriptor (a test's captured stdout)
        pass


def _main(argv: list[str]) -> int:
    parser, modules, subparsers = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 2
    # before JAX starts its backend: this process compiles many small programs
    os.environ["XLA_FLAGS"] = with_fast_cpu_compilation(os.environ.get("XLA_FLAGS", ""))
    # figures go to files only: the environment's backend (a GUI's, a bogus name: matplotlib
    # refused it on import, with a traceback) is none of the command's business
    os.environ["MPLBACKEND"] = "Agg"
    try:
        import jax  # after parsing: --help and --version stay fast

        jax.config.update("jax_enable_x64", True)
    except (ValueError, TypeError) as e:  # JAX_ENABLE_X64=junk, JAX_NUM_CPU_DEVICES=junk: read on import
        print(
            f"heliojax {args.command}: error: JAX does not start with this environment: {one_line(str(e), 300)}",
            file=sys.stderr,
        )
        return 2
    platforms = os.environ.get("JAX_PLATFORMS", "").strip()
    if platforms:  # a backend named but not usable here fails on the first array, deep in a command
        try:
            jax.devices()
        except Exception as e:  # RuntimeError (unknown backend), AssertionError (CUDA without a GPU), ...
            detail = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
            print(
                f"heliojax {args.command}: error: JAX_PLATFORMS={platforms[:60]}: JAX cannot start it here "
                f"({detail}); unset JAX_PLATFORMS or set it to cpu",
                file=sys.stderr,
            )
            return 2
    try:
        if getattr(args, "config", None) is not None:
            module = modules[args.command]
            partners = getattr(module, "PARTNERS", None)
            outputs = (*getattr(module, "OUTPUT_FILES", ()), *getattr(module, "OUTPUT_DIRS", ()))
            _apply_config(subparsers[args.command], args.command, args.config, modules, args, partners, outputs)
            args = parser.parse_args(argv)
        module = modules[args.command]
        logger = configure_logging(bool(getattr(args, "quiet", False)))
        if hasattr(module, "default_outputs"):  # outputs whose default depends on the inputs
            module.default_outputs(args)
        inside = module.outputs_inside(args) if hasattr(module, "outputs_inside") else ()
        outputs = (*getattr(module, "OUTPUT_FILES", ()), *getattr(module, "OUTPUT_DIRS", ()))
        check_output_paths(args, getattr(module, "OUTPUT_FILES", ()), getattr(module, "OUTPUT_DIRS", ()), inside)
        check_input_paths(getattr(subparsers[args.command], "options", {}), args, outputs, inside)
        if getattr(args, "quiet", False):  # no bars (INFO is off): nothing to share stderr with
            code = int(module.run(args) or 0)
        else:
            from tqdm.contrib.logging import logging_redirect_tqdm

            with logging_redirect_tqdm(loggers=[logger]):  # messages and progress bars share stderr
                code = int(module.run(args) or 0)
        if code == 0:
            remember_programs(args.command)
        return code
    except HeliojaxError as e:
        print(f"heliojax {args.command}: error: {_config_keys_named(str(e), args)}", file=sys.stderr)
        return 2
    except OSError as e:  # a file that vanished or turned unwritable while running
        return _os_error(args.command, e)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
