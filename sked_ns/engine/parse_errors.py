"""`ns-train sked`'s command-line mistakes as one `error:` line, like every other SKED command's.

nerfstudio parses `ns-train`'s arguments with tyro, which draws a multi-line box for a mistyped flag. tyro
offers a hook that fires just before it reports a parse failure (`tyro._errors.on_parse_error`, a context
variable): set only when the process is `ns-train sked*`, so every other method keeps tyro's box. The hook
module is private to tyro; where it is missing or its events change shape, tyro's own box is shown instead.
"""

from __future__ import annotations

import dataclasses
import difflib
import sys
from pathlib import Path
from typing import Iterator, Optional, Sequence

from sked_ns.engine.base_scene import dataparser_name
from sked_ns.errors import one_line

TRAIN_COMMANDS = ("ns-train", "train.py")
"""`sys.argv[0]` of nerfstudio's trainer: its console script, or `python -m nerfstudio.scripts.train`."""


def sked_train_method(argv: Sequence[str], methods: Sequence[str]) -> Optional[str]:
    """The SKED method this process trains (`ns-train sked ...`), or None for any other command or method."""
    if len(argv) < 2 or Path(argv[0]).name not in TRAIN_COMMANDS:
        return None
    return argv[1] if argv[1] in methods else None


SUGGESTIONS = 3
"""Close flags named after an unrecognised one (tyro's box lists them too)."""


DATAPARSER = "--pipeline.datamanager.dataparser."
"""nerfstudio gives the dataparser's fields after its subcommand, without this prefix."""


def flags_of(config, prefix: str = "--") -> Iterator[str]:
    """The flags tyro derives from a config: each field by its dotted path, `_` written `-` (the dataparser's as
    `nerfstudio-data --field`)."""
    for item in dataclasses.fields(config):
        if not item.init or item.name.startswith("_"):
            continue
        flag = prefix + item.name.replace("_", "-")
        value = getattr(config, item.name, None)
        if flag + "." == DATAPARSER:
            yield from flags_of(value, dataparser_name(value) + " --")
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from flags_of(value, flag + ".")
        else:
            yield flag


def last_word(flag: str) -> str:
    return flag.rsplit("--", 1)[-1].rsplit(".", 1)[-1]


def close_flags(token: str, flags: Sequence[str]) -> list:
    """The flags a mistyped one most likely meant: those ending in the same word, else the same group's nearest
    spellings, else the nearest of all."""
    same_word = [flag for flag in flags if last_word(flag) == last_word(token) and flag != token]
    if same_word:
        return same_word[:SUGGESTIONS]
    group = token.rsplit(".", 1)[0] + "." if "." in token else "--"
    siblings = {last_word(flag): flag for flag in flags
                if (flag.startswith(group) and "." not in flag[len(group):]) or (group == "--" and "." not in flag)}
    near = difflib.get_close_matches(last_word(token), list(siblings), n=SUGGESTIONS, cutoff=0.75)
    if near:
        return [siblings[word] for word in near]
    return difflib.get_close_matches(token, flags, n=SUGGESTIONS, cutoff=0.85)


def _flag(argument) -> str:
    names = getattr(getattr(argument, "lowered", None), "name_or_flags", None)
    if names:
        return "/".join(names)
    return argument.display_name()


def unrecognized(tokens: Sequence[str], flags: Sequence[str]) -> str:
    options = [token for token in tokens if token.startswith("-")] or list(tokens)
    said = f"unrecognized option{'s' if len(options) > 1 else ''} {' '.join(options)}"
    meant = [flag for option in options if option.startswith("--") for flag in close_flags(option, flags)]
    if any(option in flags for option in options):  # a real flag in the wrong place (before or after a subcommand)
        said += (" at that place (the edit's options come before the dataparser's name, the dataparser's after it: "
                 "ns-train sked --prompt ... nerfstudio-data --data ...)")
    elif meant:
        said += f" (did you mean {' or '.join(dict.fromkeys(meant))}?)"
    return said


def describe(event, flags: Sequence[str] = ()) -> Optional[str]:
    """What was wrong, in words a user acts on; None for an event this does not know (tyro's box is shown)."""
    from tyro import _errors as events

    if isinstance(event, events.UnrecognizedArgs):
        return unrecognized(event.tokens, flags)
    if isinstance(event, events.MissingArgs):
        return "missing " + ", ".join(_flag(item.arg) for item in event.missing_arguments)
    if isinstance(event, events.InvalidChoice):
        choices = ", ".join(str(choice) for choice in event.argument.lowered.choices or ())
        return f"{_flag(event.argument)}: invalid choice {event.value!r} (choose from {choices})"
    if isinstance(event, events.BadValue):
        expected = event.argument.lowered.nargs
        return f"{_flag(event.argument)}: missing value" + (f" ({expected} expected)" if isinstance(expected, int)
                                                           else "")
    if isinstance(event, events.InstantiationFailure):
        where = f"{_flag(event.argument)}: " if event.argument is not None else ""
        return where + one_line(event.message)
    if isinstance(event, events.MutexConflict):
        return f"{event.first_token} and {event.second_token} cannot be given together"
    if isinstance(event, events.SubcommandConflict):
        return (f"{event.attempted} comes too late: {event.trigger_flag} already chose {event.already_selected}; "
                f"put {event.attempted} before it")
    return None


def one_line_hook(command: str, config=None):
    """The hook for `command` (e.g. `ns-train sked`, whose config names its flags): one line on stderr, then exit
    status 2 as tyro's own."""

    def hook(event) -> None:
        try:
            detail = describe(event, sorted(set(flags_of(config))) if config is not None else ())
        except Exception:  # an event of another shape: tyro's own report is better than none
            return
        if detail is None:
            return
        print(f"error: {command}: {detail} (see {command} --help).", file=sys.stderr, flush=True)
        raise SystemExit(2)

    return hook


def install_for_sked_train(methods, argv: Optional[Sequence[str]] = None) -> bool:
    """Make `ns-train <SKED method>`'s parse errors one line (`methods`: name -> MethodSpecification); nothing for
    any other process. True if installed."""
    method = sked_train_method(sys.argv if argv is None else argv, methods)
    if method is None:
        return False
    try:
        from tyro._errors import _parse_error_hook
    except ImportError:  # a tyro without the hook: its box stays
        return False
    # Read when tyro.cli parses, later in this same context.
    _parse_error_hook.set(one_line_hook(f"ns-train {method}", methods[method].config))
    return True
