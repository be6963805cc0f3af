"""``--config FILE`` and ``--dump-config`` for every verb: a run's options from a TOML or JSON file.

One place serves every verb, from the verb's own ``argparse`` parser (nothing is declared twice):

* ``--config FILE`` reads a flat table whose keys are the verb's long option names (``max-distance``
  or ``max_distance``) and positional names (``graph``); the file's values become the parser's
  defaults, then the command line overrides them. Each value is checked before any work exactly as
  the command line checks it (the option's own ``type=``, its ``choices``, its number of values), and
  must have the file type the option takes: a boolean for a flag (``no-planes = true`` is
  ``--no-planes`` given), a number or a string for an option with a value, a list for an option with
  several values or a repeatable one. An unknown key, a wrong type or a refused value stops the run
  with one line naming the key and the file, exit status 2. Options the verb requires (``--out``)
  may come from the file.
* A ``result.json`` of an earlier run is a config too: the verbs whose record holds
  ``provenance.arguments`` (the run's options in this same form, written by
  :func:`minegeo._provenance.provenance` from :data:`minegeo._provenance.CLI_ARGUMENTS`, which
  :func:`minegeo.cli.main` sets) repeat that run; give a new ``--out`` on the command line to keep
  the first run's outputs.
* ``--dump-config`` prints the verb's options with their values (the defaults, or those of the
  ``--config`` file and of the options given with it) as TOML on stdout, each with its type and help
  as comments, and exits 0 without needing the required options. Read back with ``--config`` it
  gives the same parsed options. ``--dump-config json`` prints the same as JSON.

TOML is read with :mod:`tomllib` (Python 3.11 and later); on Python 3.10 a TOML file is refused with
a line saying to use JSON. Files are read with the bounds of :func:`minegeo.io.limits.read_file_bytes`
(regular files, at most :data:`MAX_CONFIG_BYTES`) and JSON with the strict loader of
:mod:`minegeo.io.jsonio`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

#: largest config file read (a result.json of a long SLAM run with every input hashed fits)
MAX_CONFIG_BYTES = 64 << 20

#: the options this module adds to every verb (never recorded, never read from a file)
OWN_DESTS = ("config", "dump_config")

_FLAG_ACTIONS = (argparse._StoreTrueAction, argparse._StoreFalseAction)


class ConfigError(Exception):
    """A config file that cannot be used (the message names the file and the key)."""


def _subcommands(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def add_config_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--config FILE`` and ``--dump-config [toml|json]`` to one verb's parser (to each of its
    subcommands' parsers when it has subcommands, e.g. ``minegeo intersections build``)."""
    subs = _subcommands(parser)
    if subs is not None:
        for p in dict.fromkeys(subs.choices.values()):
            add_config_options(p)
        return
    g = parser.add_argument_group("configuration file (docs/config.md)")
    g.add_argument("--config", metavar="FILE", default=None,
                   help="read the options from a TOML or JSON file (keys: the long option names; the command line "
                        "overrides the file), or repeat a run from its result.json")
    g.add_argument("--dump-config", nargs="?", const="toml", choices=("toml", "json"), default=None, metavar="FORMAT",
                   help="print every option with its value (defaults, --config and the options given) as TOML "
                        "(or json) and exit")


def verb_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The verb's own options and positionals (not ``--help`` nor the two config options), in order."""
    return [a for a in parser._actions
            if not isinstance(a, (argparse._HelpAction, argparse._VersionAction)) and a.dest not in OWN_DESTS
            and a.dest != argparse.SUPPRESS]


def key_of(action: argparse.Action) -> str:
    """The config key of an option: its first long option name without ``--`` (positionals: their name)."""
    if not action.option_strings:
        return action.dest.replace("_", "-")
    longs = [s for s in action.option_strings if s.startswith("--")]
    return (longs[0] if longs else action.option_strings[0]).lstrip("-")


def _key_table(parser) -> dict[str, argparse.Action]:
    table: dict[str, argparse.Action] = {}
    for a in verb_actions(parser):
        names = {key_of(a), a.dest.replace("_", "-")}
        names |= {s.lstrip("-") for s in a.option_strings if s.startswith("--")}
        for n in names:
            table[n.replace("_", "-")] = a
    return table


def _is_flag(a: argparse.Action) -> bool:
    return isinstance(a, _FLAG_ACTIONS)


def _is_append(a: argparse.Action) -> bool:
    return isinstance(a, argparse._AppendAction)


def _n_values(a: argparse.Action) -> int | None:
    """How many values the option takes as a list (None: one value)."""
    if isinstance(a.nargs, int) and not _is_append(a):
        return a.nargs
    return None


# ------------------------------------------------------------------ reading


def _describe(v: Any) -> str:
    return {bool: "a boolean", int: "a whole number", float: "a number", str: "a string", list: "a list",
            dict: "a table", type(None): "null"}.get(type(v), type(v).__name__)


def _convert_one(a: argparse.Action, v: Any, key: str, where: str) -> Any:
    """One value of option ``a`` from a file, checked as the command line checks it; the file's type
    must be the type of the parsed value (a number for a numeric option, a string for any other)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        what = "a string" if a.type is None else "one value (a number, or a string for a text option)"
        raise ConfigError(f"{where}: key {key!r} takes {what}, got {_describe(v)} {json.dumps(v)}")
    if a.type is None and not isinstance(v, str):
        raise ConfigError(f"{where}: key {key!r} must be a string, got {_describe(v)} {v!r}")
    text = repr(v) if isinstance(v, float) else str(v)
    parsed = v
    if a.type is not None:
        try:
            parsed = a.type(text)
        except (argparse.ArgumentTypeError, TypeError, ValueError) as exc:
            msg = str(exc) if isinstance(exc, argparse.ArgumentTypeError) else f"invalid value {text!r}"
            raise ConfigError(f"{where}: key {key!r}: {msg}") from None
        numeric = isinstance(parsed, (int, float)) and not isinstance(parsed, bool)
        if numeric and isinstance(v, str):
            raise ConfigError(f"{where}: key {key!r} must be a number, got a string {v!r} (write it without quotes)")
        if not numeric and not isinstance(v, str):
            raise ConfigError(f"{where}: key {key!r} must be a string, got {_describe(v)} {v!r} (write it in quotes)")
    if a.choices is not None and parsed not in a.choices:
        raise ConfigError(f"{where}: key {key!r}: invalid choice {parsed!r} (choose from "
                          f"{', '.join(repr(c) for c in a.choices)})")
    return parsed


def convert(a: argparse.Action, v: Any, key: str, where: str) -> Any:
    """The parsed value (as ``argparse`` would store it) of option ``a`` given ``v`` in a file.

    Raises
    ------
    ConfigError
        ``v`` has the wrong type for the option or is refused by its ``type``/``choices``.
    """
    if _is_flag(a):
        if not isinstance(v, bool):
            raise ConfigError(f"{where}: key {key!r} is a flag: it must be true or false, got {_describe(v)} {v!r}")
        return v if isinstance(a, argparse._StoreTrueAction) else not v
    if v is None:
        if a.default is None:
            return None
        raise ConfigError(f"{where}: key {key!r} must have a value (null is only for options without a default)")
    n = _n_values(a)
    if n is not None or _is_append(a):
        if not isinstance(v, list):
            raise ConfigError(f"{where}: key {key!r} takes a list of {n if n else 'one or more'} values, "
                              f"got {_describe(v)} {v!r}")
        if n is not None and len(v) != n:
            raise ConfigError(f"{where}: key {key!r} takes exactly {n} values, got {len(v)}")
        return [_convert_one(a, x, key, where) for x in v]
    return _convert_one(a, v, key, where)


def _read_table(path: Path) -> dict:
    """The top-level table of a TOML or JSON file (JSON when it is named ``.json`` or starts with ``{``)."""
    from minegeo.io.limits import read_file_bytes

    data = read_file_bytes(path, max_bytes=MAX_CONFIG_BYTES, what="config file (TOML or JSON)")
    is_json = path.suffix.lower() == ".json" or data.lstrip()[:1] == b"{"
    if is_json:
        from minegeo.io.jsonio import load_json_text

        doc = load_json_text(data, path, max_bytes=MAX_CONFIG_BYTES, allow_nonfinite=True)
    else:
        try:
            import tomllib
        except ImportError:  # Python 3.10
            raise ConfigError(f"config file {path}: reading TOML needs Python 3.11 or later (tomllib), this is Python "
                              f"{sys.version_info[0]}.{sys.version_info[1]}: give the options as JSON "
                              "(write one with --dump-config json)") from None
        try:
            doc = tomllib.loads(data.decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise ConfigError(f"config file {path}: not UTF-8 text (byte {exc.start}); a config file is TOML or JSON") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config file {path}: not valid TOML ({exc}); a config file is TOML or JSON") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"config file {path}: a config file holds a table of options (key = value), not {_describe(doc)}")
    return doc


def _recorded_command(doc: dict) -> str | None:
    """The verb a result record names (``command``, ``verb`` or ``tool``: ``"intersections build"``,
    ``"info"``, ``"minegeo adjust"``), or None."""
    for field in ("command", "verb", "tool"):
        v = doc.get(field)
        if isinstance(v, str) and v.strip():
            words = v.split()
            return words[1] if words[0] == "minegeo" and len(words) > 1 else words[0]
    return None


def _from_result(doc: dict, verb: str, where: str) -> dict:
    """The options recorded in a ``result.json`` of ``minegeo VERB`` (its ``provenance.arguments``)."""
    command = _recorded_command(doc)
    if command is not None and command != verb:
        raise ConfigError(f"{where} is the result of `minegeo {command}`, not of `minegeo {verb}`")
    args = doc["provenance"].get("arguments")
    if "batch" in doc and not isinstance(args, dict):
        raise ConfigError(f"{where} is the record of one scan of `minegeo localize-batch`: repeat the batch from its "
                          "batch_result.json, or give the scan to `minegeo localize` with the batch's options")
    if not isinstance(args, dict):
        raise ConfigError(f"{where}: this result records no options (provenance.arguments): it was written "
                          f"before minegeo recorded them, or `minegeo {verb}` does not record them yet "
                          "(docs/config.md lists the verbs that do)")
    return args


def is_result_record(doc: dict) -> bool:
    """Whether a parsed file is a minegeo result record (it has a ``provenance`` table; an options
    file never has: no verb has a ``--provenance`` option)."""
    return isinstance(doc.get("provenance"), dict)


def load_config(path, parser: argparse.ArgumentParser, verb: str) -> dict[str, Any]:
    """The parsed values (dest -> value) a config file gives for ``minegeo VERB``.

    Parameters
    ----------
    path : str or Path
        TOML or JSON file of options, or a ``result.json`` of an earlier run of the same verb.
    parser : argparse.ArgumentParser
        The verb's parser (its actions define the keys, types and checks).
    verb : str
        The verb (``result.json`` of another verb is refused).

    Raises
    ------
    ConfigError
        Unreadable file, unknown key, a key given twice (``max-distance`` and ``max_distance``), a
        wrong type or a refused value, two options of one mutually exclusive group.
    """
    path = Path(path)
    try:
        doc = _read_table(path)
    except ConfigError:
        raise
    except (OSError, ValueError) as exc:  # FileFormatError is both; FileNotFoundError, PermissionError
        from minegeo.errors import FileFormatError

        if isinstance(exc, FileFormatError):
            raise ConfigError(f"--config: {exc}") from None
        raise ConfigError(f"--config {path}: {getattr(exc, 'strerror', None) or exc}") from None
    where = f"config file {path}"
    if is_result_record(doc):
        doc = _from_result(doc, verb, where)
        where = f"{where} (its provenance.arguments)"
    table = _key_table(parser)
    values: dict[str, Any] = {}
    seen: dict[str, str] = {}
    for key, v in doc.items():
        a = table.get(str(key).replace("_", "-"))
        if a is None:
            near = sorted(k for k in {key_of(x) for x in verb_actions(parser)})
            raise ConfigError(f"{where}: unknown key {key!r}: `{parser.prog}` has no option --{key} "
                              f"(its keys: {', '.join(near)}; see {parser.prog} --dump-config)")
        if a.dest in seen:
            raise ConfigError(f"{where}: keys {seen[a.dest]!r} and {key!r} are the same option")
        seen[a.dest] = key
        if v is None and a.required:
            continue  # a required option left empty (as --dump-config json writes it): the command line gives it
        values[a.dest] = convert(a, v, key, where)
    for group in parser._mutually_exclusive_groups:
        given = [key_of(a) for a in group._group_actions if a.dest in values and values[a.dest] != a.default]
        if len(given) > 1:
            raise ConfigError(f"{where}: keys {' and '.join(map(repr, given))} cannot be used together")
    return values


# ------------------------------------------------------------------ writing


def _toml_str(s: str) -> str:
    out = []
    for ch in s:
        o = ord(ch)
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif o < 0x20 or o == 0x7F:
            out.append(f"\\u{o:04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def toml_value(v: Any) -> str:
    """One TOML value (flat: booleans, integers, floats, strings and lists of them)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)  # shortest text that reads back to the same float: '0.3', '1e-05', '1.0'
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {type(v).__name__} {v!r}")


def file_value(a: argparse.Action, v: Any) -> Any:
    """The file form of a parsed value (flags: whether the flag is given; lists as lists)."""
    if _is_flag(a):
        return bool(v) if isinstance(a, argparse._StoreTrueAction) else not v
    if isinstance(v, tuple):
        return list(v)
    if isinstance(v, Path):
        return str(v)
    return v


def arguments_record(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict[str, Any]:
    """The verb's parsed options in the config-file form (key -> value, ``None`` for unset)."""
    return {key_of(a): file_value(a, getattr(args, a.dest, a.default)) for a in verb_actions(parser)}


def _type_text(a: argparse.Action) -> str:
    if _is_flag(a):
        return "flag: true or false"
    base = "string" if a.type is None else getattr(a.type, "__name__", "value")
    if a.choices is not None:
        base = "one of " + ", ".join(repr(c) for c in a.choices)
    n = _n_values(a)
    if n is not None:
        return f"list of {n} x {base}"
    if _is_append(a):
        return f"list of {base}"
    return base


def dump_toml(parser: argparse.ArgumentParser, args: argparse.Namespace, verb: str,
              required: set[str] | frozenset[str] = frozenset()) -> str:
    """The verb's options as a TOML file: ``key = value`` lines, each after its type and help.

    Options without a value (``None``) are written commented out, so the file read back leaves them
    unset; ``[required]`` marks those the command line or the file must give.
    """
    from minegeo import __version__

    lines = [f"# {parser.prog}: options (minegeo {__version__}); use with: {parser.prog} --config FILE",
             "# keys are the long option names; the command line overrides the file", ""]
    for a in verb_actions(parser):
        v = file_value(a, getattr(args, a.dest, a.default))
        req = " [required]" if a.dest in required or a.required else ""
        lines.append(f"# {_type_text(a)}{req}")
        help_text = "" if a.help == argparse.SUPPRESS else " ".join(str(a.help or "").split())
        if help_text:
            lines.append(f"# {help_text}")
        key = key_of(a)
        if v is None:
            lines.append(f"# {key} =")
        else:
            lines.append(f"{key} = {toml_value(v)}")
        lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------ the CLI hook


def options_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The parser holding the options of the command ``args`` was parsed for: the verb's parser, or
    that of its subcommand (``minegeo intersections build``)."""
    subs = _subcommands(parser)
    while subs is not None and getattr(args, subs.dest, None) in subs.choices:
        parser = subs.choices[getattr(args, subs.dest)]
        subs = _subcommands(parser)
    return parser


def _leaf(parser: argparse.ArgumentParser, rest: list[str]) -> tuple[argparse.ArgumentParser, list[str]]:
    """The subcommand parser a command line selects (its first positional naming one) and its arguments."""
    subs = _subcommands(parser)
    while subs is not None:
        i = next((i for i, t in enumerate(rest) if not t.startswith("-")), None)
        if i is None or rest[i] not in subs.choices:
            break
        parser, rest = subs.choices[rest[i]], rest[i + 1:]
        subs = _subcommands(parser)
    return parser, rest


def _verb_argv(argv: list[str], verb: str) -> list[str]:
    return argv[argv.index(verb) + 1:]


def _pre_parse(rest: list[str]) -> argparse.Namespace:
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    add_config_options(pre)
    ns, _ = pre.parse_known_args(rest)
    return ns


def parse_with_config(parser: argparse.ArgumentParser, argv: list[str], verb: str | None):
    """``parser.parse_args(argv)`` with ``--config`` and ``--dump-config`` applied for the verb.

    Returns
    -------
    (argparse.Namespace, str | None)
        The parsed arguments, and the text to print instead of running (``--dump-config``), or None.
        A config problem exits with status 2 through the verb parser's one-line ``error``.
    """
    if verb is None or verb not in getattr(parser, "_verb_parsers", {}):
        return parser.parse_args(argv), None
    sub, rest = _leaf(parser._verb_parsers[verb], _verb_argv(argv, verb))
    if _subcommands(sub) is not None:  # no subcommand named: argparse says which are needed
        return parser.parse_args(argv), None
    try:
        pre = _pre_parse(rest)
    except SystemExit:  # a malformed --dump-config value: the verb parser says it in full
        pre = argparse.Namespace(config=None, dump_config=None)
    values: dict[str, Any] = {}
    if pre.config is not None:
        try:
            values = load_config(pre.config, sub, verb)
        except ConfigError as exc:
            sub.error(str(exc))
    actions = {a.dest: a for a in verb_actions(sub)}
    original = {d: a.default for d, a in actions.items()}
    required = {d for d, a in actions.items() if a.required}
    for dest, v in values.items():
        a = actions[dest]
        if _is_append(a):
            continue  # applied after parsing: a repeatable option given on the command line replaces the file's list
        a.default = v
        a.required = False
        if not a.option_strings:
            a.nargs = "?"
    if pre.dump_config is not None:
        for a in actions.values():  # dumping needs no required option
            a.required = False
            if not a.option_strings and a.nargs is None:
                a.nargs = "?"
    args = parser.parse_args(argv)
    if args.config != pre.config or args.dump_config != pre.dump_config:
        sub.error("write --config and --dump-config in full (not abbreviated)")
    for dest, v in values.items():
        if _is_append(actions[dest]) and getattr(args, dest) == original[dest]:
            setattr(args, dest, v)
    for group in sub._mutually_exclusive_groups:  # a member given on the command line wins over the file's
        members = group._group_actions
        on_cli = [m for m in members if getattr(args, m.dest) != values.get(m.dest, original[m.dest])]
        if on_cli:
            for m in members:
                if m not in on_cli and m.dest in values:
                    setattr(args, m.dest, original[m.dest])
    if pre.dump_config is not None:
        if pre.dump_config == "json":
            return args, json.dumps(arguments_record(sub, args), indent=2) + "\n"
        return args, dump_toml(sub, args, verb, required)
    return args, None
