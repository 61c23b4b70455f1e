"""`ns-train sked`'s command-line mistakes as one `error:` line, like every other SKED command's.

nerfstudio parses `ns-train`'s arguments with tyro, which draws a multi-line box for a mistyped flag. tyro
offers a hook that fires just before it reports a parse failure (`tyro._errors.on_parse_error`, a context
variable): set only when the process is `ns-train sked*`, so every other method keeps tyro's box, or `ns-train
<a SKED method misspelt>`, where it says only that the method meant is SKED's. The hook module is private to tyro;
where it is missing or its events change shape, tyro's own box is shown instead.

tyro reads a command line in order: the edit's options, then a subcommand (a guidance, the dataparser's name)
and the options of what it chose, each only after its subcommand. The hook reads the method's config as tyro
does (command_line.py: hidden fields left out, each subcommand's own options) and the words typed, so a line says
which of those was wrong: a misspelt flag or subcommand (not the options after it, unrecognised for that alone), an
option of another guidance, a flag that swallowed the next one as its value, a word processor's dash.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import sys
import unicodedata
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

from sked_ns.engine.command_line import DATAPARSER_GROUP, CommandLine, bare
from sked_ns.errors import one_line
from sked_ns.method.options import SkedOptions

TRAIN_COMMANDS = ("ns-train", "train.py")
"""`sys.argv[0]` of nerfstudio's trainer: its console script, or `python -m nerfstudio.scripts.train`."""


def sked_train_method(argv: Sequence[str], methods: Sequence[str]) -> Optional[str]:
    """The SKED method this process trains (`ns-train sked ...`), or None for any other command or method."""
    if len(argv) < 2 or Path(argv[0]).name not in TRAIN_COMMANDS:
        return None
    return argv[1] if argv[1] in methods else None


SUGGESTIONS = 3
"""Close flags named after an unrecognised one (tyro's box lists them too)."""

MODEL = "--pipeline.model."
"""An edit's model options: those tyro hides are the base's, copied from it."""

TYPOGRAPHIC_DASHES = "\u2010\u2011\u2012\u2013\u2014\u2015\u2212"
"""What word processors and chat windows make of `--`: Unicode hyphens, the en and em dashes, the minus sign."""

KINDS = {"INT": ("an integer", "integers"), "FLOAT": ("a number", "numbers"), "STR": ("text", "texts"),
         "PATH": ("a path", "paths")}
"""tyro's metavars in words: one value, several."""


def last_word(flag: str) -> str:
    return flag.rsplit("--", 1)[-1].rsplit(".", 1)[-1]


def close_flags(token: str, flags: Sequence[str]) -> list:
    """The flags a mistyped one most likely meant: those ending in the same word, else the same group's nearest
    spellings, else the nearest of all."""
    same_word = [flag for flag in flags if last_word(flag) == last_word(token) and flag != token]
    if same_word:
        return same_word[:SUGGESTIONS]
    group = token.rsplit(".", 1)[0] + "." if "." in token else "--"
    siblings = {last_word(flag): flag for flag in flags if (bare(flag).startswith(group) and "." not in
                bare(flag)[len(group):]) or (group == "--" and "." not in bare(flag))}
    near = difflib.get_close_matches(last_word(token), list(siblings), n=SUGGESTIONS, cutoff=0.75)
    if near:
        return [siblings[word] for word in near]
    return difflib.get_close_matches(token, flags, n=SUGGESTIONS, cutoff=0.85)


def _dashes(token: str) -> Optional[str]:
    """How a flag's dashes were mistyped (a word processor's dash for `--`, one hyphen), or None."""
    dashes = re.match(f"[-{TYPOGRAPHIC_DASHES}]+", token)
    if dashes is None or dashes.group() == "--" or not token[dashes.end():][:1].isalpha():
        return None
    typographic = [dash for dash in dashes.group() if dash in TYPOGRAPHIC_DASHES]
    if typographic:
        return f"a typographic dash ({unicodedata.name(typographic[0]).lower()}, what word processors make of --)"
    return f"{len(dashes.group())} hyphens" if len(dashes.group()) > 1 else "one hyphen"


def _subcommand_advice(token: str, line: CommandLine, words: Sequence[str]) -> Optional[str]:
    group = line.subcommands.get(token)
    if group is not None:
        chosen = line.chosen(group, words)
        if chosen not in (None, token):
            return f"{token}: {chosen} was already given (one {group.rsplit('.', 1)[-1]} at a time)"
        return (f"{token} at that place (a subcommand comes after the edit's options and before the dataparser's "
                f"name; its own options follow it)")
    near, choices = _near_subcommands(token, line)
    if not near and not choices:
        return None
    return f"unknown subcommand {token}" + (f" (did you mean {' or '.join(near)}?)" if near else "") + choices


def _near_subcommands(token: str, line: CommandLine) -> Tuple[List[str], str]:
    """The subcommands a word not offered most likely meant, and, where its group is right, the group's choices."""
    if token[:1] in "-" + TYPOGRAPHIC_DASHES or token in line.subcommands:
        return [], ""
    named, group = token.rpartition(":")[2], token.rpartition(":")[0]
    if group in line.subcommands.values():  # the group is right: match the name among its subcommands
        offered = {sub.rpartition(":")[2]: sub for sub, of in line.subcommands.items() if of == group}
        near = [offered[name] for name in difflib.get_close_matches(named, list(offered), n=SUGGESTIONS, cutoff=0.6)]
        return near, f"; the {group.rsplit('.', 1)[-1]} subcommands are {', '.join(offered.values())}"
    subcommands = list(line.subcommands)
    # The nearest few, else the one nearest a shortened name (colmap-dat: colmap).
    return (difflib.get_close_matches(token, subcommands, n=SUGGESTIONS, cutoff=0.8)
            or difflib.get_close_matches(token, subcommands, n=1, cutoff=0.7)), ""


def _misspelt_subcommand(token: str, line: CommandLine) -> bool:
    return any(_near_subcommands(token, line))


def _without_what_follows_misspelt_subcommands(tokens: Sequence[str], line: CommandLine) -> List[str]:
    """The words after a misspelt subcommand are its options, unrecognised only because it was: left out (one
    mistake said, not its consequences), up to the next word that is itself a misspelt subcommand."""
    kept, skipping = [], False
    for at, token in enumerate(tokens):
        value = at > 0 and tokens[at - 1][:2] == "--" and "=" not in tokens[at - 1]  # an unrecognised flag's value
        if not value and _misspelt_subcommand(token, line):
            kept.append(token)
            skipping = True
        elif not skipping:
            kept.append(token)
    return kept


def _misplaced(flag: str, line: CommandLine, words: Sequence[str]) -> Optional[str]:
    """Why a flag tyro offers somewhere was not taken where it was typed."""
    after = line.where(flag)
    if not after:
        return None
    if "" in after:
        return (f"{flag} at that place (the edit's options come before the subcommands: ns-train sked --prompt ... "
                f"[pipeline.model.guidance:<name> ...] nerfstudio-data --data ...)")
    group = line.subcommands.get(after[0])
    if group == DATAPARSER_GROUP:
        return f"{flag} is an option of the dataparser: it goes after its name ({after[0]} {flag} ...)"
    kind, chosen = group.rsplit(".", 1)[-1], line.chosen(group, words)
    owners = " and ".join(sub + (f", the default {kind}" if sub == line.defaults.get(group) else "") for sub in after)
    if chosen in after:
        return f"{flag} at that place: it goes right after {chosen}, before the dataparser's name"
    if chosen is not None:
        return (f"the {kind} {chosen} has no setting {flag} (a setting of {owners}); its settings are "
                f"{', '.join(line.options_of(chosen)) or 'none'}")
    return f"{flag} is a setting of {owners}: name the {kind} before it ({after[0]} {flag} ...)"


def _advice(token: str, line: CommandLine, words: Sequence[str]) -> Optional[str]:
    """What was wrong with one unrecognised word, where it is more than a misspelling; None for those."""
    how = _dashes(token)
    if how is not None:
        spelt = token.split("=", 1)[0]
        meant = "--" + spelt.lstrip("-" + TYPOGRAPHIC_DASHES)
        near = [] if line.where(meant) else close_flags(meant, line.flags)
        if near:
            return f"{spelt} begins with {how}, not two ASCII hyphens (did you mean {' or '.join(near)}?)"
        if line.where(meant) or "typographic" in how:
            return f"{spelt} begins with {how}: type {meant} (two ASCII hyphens)"
        return None  # an unknown flag, whatever its dashes
    if not token.startswith("-"):
        return _subcommand_advice(token, line, words)
    flag = token.split("=", 1)[0]
    if flag.startswith(MODEL) and any(flag == hidden or flag.startswith(hidden + ".") for hidden in line.hidden):
        if flag[len(MODEL):].replace("-", "_") in {option.name for option in dataclasses.fields(SkedOptions)}:
            return f"{flag} is not an option: the edit sets it itself"
        return f"{flag} is the base's: an edit keeps its base's model settings (train the base with it instead)"
    return _misplaced(flag, line, words)


def _options(tokens: Sequence[str], line: CommandLine) -> List[str]:
    """The unrecognised words that were meant as flags or subcommands, not values."""
    meant = [token for token in tokens if token[:1] in "-" + TYPOGRAPHIC_DASHES or ":" in token
             or token in line.subcommands or _misspelt_subcommand(token, line)]
    return meant or list(tokens)


def unrecognized(tokens: Sequence[str], line: CommandLine, words: Sequence[str] = ()) -> str:
    swallowed = [at for at in range(1, len(words)) if words[at] in line.subcommands and words[at - 1][:2] == "--"
                 and "=" not in words[at - 1]]
    if swallowed:  # the options after the subcommand are unrecognised only because it was read as a flag's value
        flag, subcommand = words[swallowed[0] - 1], words[swallowed[0]]
        return f"{flag} needs a value; it was followed by {subcommand}, which it took as its value"
    options, said, plain = _options(_without_what_follows_misspelt_subcommands(tokens, line), line), [], []
    for option in options:
        advice = _advice(option, line, words)
        (said if advice else plain).append(advice or option)
    if plain:
        meant = [flag for option in plain if option.startswith("--") for flag in close_flags(option, line.flags)]
        said.insert(0, f"unrecognized option{'s' if len(plain) > 1 else ''} {' '.join(plain)}"
                       + (f" (did you mean {' or '.join(dict.fromkeys(meant))}?)" if meant else ""))
    return "; ".join(said)


def _flag(argument) -> str:
    names = getattr(getattr(argument, "lowered", None), "name_or_flags", None)
    if names:
        return "/".join(names)
    return argument.display_name()


def _kind(argument) -> str:
    """The values an argument takes, in words: `an integer`, `2 numbers`, `one of cpu, cuda, mps`."""
    lowered = argument.lowered
    choices = [str(choice) for choice in lowered.choices or ()]
    if sorted(choices) == ["False", "True"]:
        return "True or False"
    if choices:
        return "one of " + ", ".join(choices)
    metavar = str(lowered.metavar or "")
    optional = metavar.startswith("{None}|")
    names = metavar.removeprefix("{None}|").split()
    if names and len(set(names)) == 1 and names[0] in KINDS:
        one, several = KINDS[names[0]]
        said = one if len(names) == 1 else f"{len(names)} {several}"
    else:
        said = metavar or "a value"
    return said + (" or None" if optional else "")


def _typed_after(argument, words: Sequence[str]) -> Optional[List[str]]:
    """The words typed after the argument's last flag (its `=value` alone where given so); None if it is not
    among the words."""
    names = set(getattr(argument.lowered, "name_or_flags", None) or ())
    for at in range(len(words) - 1, -1, -1):
        name, equals, value = words[at].partition("=")
        if name in names:
            return [value] if equals else list(words[at + 1:])
    return None


def _not_a_value(word: str, line: CommandLine) -> bool:
    return (word == "" or word in line.subcommands or word[:1] in TYPOGRAPHIC_DASHES
            or (word.startswith("-") and word.lstrip("-")[:1].isalpha()))


def _needs_value(argument, after: Sequence[str], line: CommandLine) -> str:
    count = argument.lowered.nargs if isinstance(argument.lowered.nargs, int) else 1
    given = []
    for word in after[:count]:
        if _not_a_value(word, line):
            break
        given.append(word)
    said = f"{_flag(argument)} needs {'a value' if count == 1 else f'{count} values'} ({_kind(argument)})"
    then = after[len(given)] if len(after) > len(given) else ""
    if given:
        return said + f"; it was given only {' '.join(given)}" + (f", then {then}" if then else "")
    return said + (f"; it was followed by {then}" if then else "; none was given")


def _bad_value(argument, value: str, line: CommandLine, words: Sequence[str]) -> str:
    """A value a flag cannot take: the next flag or subcommand it swallowed, or a word it does not read."""
    after = _typed_after(argument, words)
    if _not_a_value(value, line):
        return _needs_value(argument, after if after and after[0] == value else [value], line)
    choices = [str(choice) for choice in argument.lowered.choices or ()]
    near = ([choice for choice in choices if choice.lower() == value.lower()]
            or [choice for choice in choices if value and value.lower() in choice.lower()]
            or difflib.get_close_matches(value, choices, n=SUGGESTIONS, cutoff=0.75))
    return f"{_flag(argument)} takes {_kind(argument)}, not {value!r}" + (
        f" (did you mean {' or '.join(near)}?)" if near else "")


def _failed(event, line: CommandLine, words: Sequence[str]) -> str:
    """A value tyro parsed but could not build: an integer flag given a word, or given the next subcommand."""
    argument = event.argument
    if argument is None:
        return one_line(event.message)
    after, count = _typed_after(argument, words), argument.lowered.nargs
    if after is None or not isinstance(count, int):
        return f"{_flag(argument)}: {one_line(event.message)}"
    if any(_not_a_value(word, line) for word in after[:count]) or len(after) < count:
        return _needs_value(argument, after, line)
    return _bad_value(argument, " ".join(after[:count]), line, words)


def describe(event, line: Optional[CommandLine] = None, words: Sequence[str] = ()) -> Optional[str]:
    """What was wrong, in words a user acts on (`words`: the command line after the method's name); None for an
    event this does not know (tyro's box is shown)."""
    from tyro import _errors as events

    line = line or CommandLine()
    if isinstance(event, events.UnrecognizedArgs):
        return unrecognized(event.tokens, line, words)
    if isinstance(event, events.MissingArgs):
        return "missing " + ", ".join(_flag(item.arg) for item in event.missing_arguments)
    if isinstance(event, events.InvalidChoice):
        return _bad_value(event.argument, event.value, line, words)
    if isinstance(event, events.BadValue):
        if event.reason == "too_few_values":
            return _needs_value(event.argument, _typed_after(event.argument, words) or [], line)
        if event.reason == "fixed":
            return (f"{_flag(event.argument)} is fixed and takes no value: leave out "
                    f"{event.offending_value!r} after it")
        return f"{_flag(event.argument)} cannot take the value it was given"
    if isinstance(event, events.InstantiationFailure):
        return _failed(event, line, words)
    if isinstance(event, events.MutexConflict):
        return f"{event.first_token} and {event.second_token} cannot be given together"
    if isinstance(event, events.SubcommandConflict):
        return (f"{event.attempted} comes too late: {event.trigger_flag} already chose {event.already_selected}; "
                f"put {event.attempted} before it")
    return None


def one_line_hook(command: str, config=None, words: Sequence[str] = ()):
    """The hook for `command` (e.g. `ns-train sked`, whose config names its flags; `words`: what followed the
    command): one line on stderr, then exit status 2 as tyro's own."""

    def hook(event) -> None:
        try:
            detail = describe(event, CommandLine.of(config) if config is not None else None, words)
        except Exception:  # an event of another shape: tyro's own report is better than none
            return
        if detail is None:
            return
        print(f"error: {command}: {detail} (see {command} --help).", file=sys.stderr, flush=True)
        raise SystemExit(2)

    return hook


METHOD_CUTOFF = 0.6
"""How close a word that is no method must be to a SKED method's name to be taken for it (skd, sked-fst)."""


def misspelt_sked_method(argv: Sequence[str], methods: Sequence[str]) -> Optional[str]:
    """The SKED method `ns-train <word>` most likely meant, where the word is none of them but near one; else None."""
    if len(argv) < 2 or Path(argv[0]).name not in TRAIN_COMMANDS or argv[1] in methods or argv[1][:1] == "-":
        return None
    near = difflib.get_close_matches(argv[1].lower(), list(methods), n=1, cutoff=METHOD_CUTOFF)
    return near[0] if near else None


def unknown_method_hook(word: str, sked_methods: Sequence[str]):
    """For `ns-train <word>`, where the word is near a SKED method's name: tyro's report that the word is no method
    becomes one line naming the method meant, when no registered method is nearer (a stock method's misspelling
    keeps tyro's box); every other event, and any command where the word is a method, falls through to tyro."""

    def hook(event) -> None:
        from tyro import _errors as events

        if not (isinstance(event, events.UnrecognizedArgs) and event.tokens and event.tokens[0] == word):
            return
        try:
            from nerfstudio.configs.method_configs import all_methods
        except Exception:  # nerfstudio's registry is not there to compare with: tyro's box
            return
        near = difflib.get_close_matches(word.lower(), list(all_methods), n=1, cutoff=METHOD_CUTOFF)
        if word in all_methods or not near or near[0] not in sked_methods:
            return
        print(f"error: ns-train: no method {word} (did you mean ns-train {near[0]}? SKED's methods are "
              f"{', '.join(sked_methods)}; see ns-train --help for all).", file=sys.stderr, flush=True)
        raise SystemExit(2)

    return hook


def install_for_sked_train(methods, argv: Optional[Sequence[str]] = None) -> bool:
    """Make `ns-train <SKED method>`'s parse errors one line (`methods`: name -> MethodSpecification), and
    `ns-train <a SKED method misspelt>`'s unknown method; nothing for any other process. True if installed."""
    argv = sys.argv if argv is None else argv
    method = sked_train_method(argv, methods)
    meant = misspelt_sked_method(argv, list(methods)) if method is None else None
    if method is None and meant is None:
        return False
    try:
        from tyro._errors import _parse_error_hook
    except ImportError:  # a tyro without the hook: its box stays
        return False
    # Read when tyro.cli parses sys.argv, later in this same context.
    if method is None:
        _parse_error_hook.set(unknown_method_hook(argv[1], list(methods)))
    else:
        _parse_error_hook.set(one_line_hook(f"ns-train {method}", methods[method].config, list(argv[2:])))
    return True
