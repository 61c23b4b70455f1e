"""What tyro offers on a method's command line, read from its config as tyro reads it: each option as typed (after
the subcommand it follows), the subcommands of each group and their defaults, and the fields it hides.
`parse_errors.py` says from it what a mistyped command line meant."""

from __future__ import annotations

import dataclasses
from typing import Any, Dict, List, Optional, Sequence, Union, get_args, get_origin, get_type_hints

from typing_extensions import Annotated

from sked_ns.engine.base_scene import dataparser_name

DATAPARSER = "--pipeline.datamanager.dataparser."
"""nerfstudio gives the dataparser's fields after its subcommand, without this prefix."""

DATAPARSER_GROUP = "dataparser"


@dataclasses.dataclass
class CommandLine:
    """What tyro offers on a method's command line, read from its config as tyro reads it."""

    flags: List[str] = dataclasses.field(default_factory=list)
    """Every option as typed, after its subcommand where it has one: `--prompt`, `nerfstudio-data --data`,
    `pipeline.model.guidance:reference --pipeline.model.guidance.target`."""
    hidden: List[str] = dataclasses.field(default_factory=list)
    """Fields tyro is told to hide (`tyro.conf.Suppress`), as flags: an edit's model settings copied from its base."""
    subcommands: Dict[str, str] = dataclasses.field(default_factory=dict)
    """Each subcommand and the group it chooses in (`pipeline.model.guidance`, or the dataparser)."""
    defaults: Dict[str, str] = dataclasses.field(default_factory=dict)
    """Each group's default subcommand (its options, too, follow it only once it is named)."""

    @classmethod
    def of(cls, config) -> "CommandLine":
        line = cls()
        line._read(config, "--", "")
        return line

    def _read(self, config, prefix: str, subcommand: str) -> None:
        hints = _type_hints(type(config))
        for item in dataclasses.fields(config):
            if item.init and not item.name.startswith("_"):
                flag = prefix + item.name.replace("_", "-")
                self._field(flag, getattr(config, item.name, None), hints.get(item.name), subcommand)

    def _field(self, flag: str, value, hint, subcommand: str) -> None:
        if _suppressed(hint):
            self.hidden.append(f"{subcommand} {flag}".lstrip())
        elif flag + "." == DATAPARSER:
            from nerfstudio.configs.dataparser_configs import all_dataparsers

            self.subcommands.update(dict.fromkeys(all_dataparsers, DATAPARSER_GROUP))
            self.defaults[DATAPARSER_GROUP] = dataparser_name(value)
            self._read(value, "--", dataparser_name(value))
        elif _subcommand_types(hint):
            group = flag[2:]
            for name, member in _subcommand_types(hint).items():
                self.subcommands[f"{group}:{name}"] = group
                if type(value) is member:
                    self.defaults[group] = f"{group}:{name}"
                chosen = value if type(value) is member else _default_instance(member)
                if chosen is not None:
                    self._read(chosen, flag + ".", f"{group}:{name}")
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            self._read(value, flag + ".", subcommand)
        elif isinstance(value, dict) and value:  # tyro offers each key of a dict given in the config
            for key, item in value.items():
                self._field(f"{flag}.{str(key).replace('_', '-')}", item, None, subcommand)
        elif not callable(value):  # a function or class is fixed: tyro offers no flag for it
            self.flags.append(f"{subcommand} {flag}".lstrip())

    def where(self, flag: str) -> List[str]:
        """The subcommands after which `flag` is offered ("" for the edit's own options)."""
        return [offered.rpartition(" ")[0] for offered in self.flags if bare(offered) == flag]

    def options_of(self, subcommand: str) -> List[str]:
        return [bare(flag) for flag in self.flags if flag.startswith(subcommand + " ")]

    def chosen(self, group: str, words: Sequence[str]) -> Optional[str]:
        """The group's subcommand among the words typed, if one is."""
        named = [word for word in words if self.subcommands.get(word) == group]
        return named[0] if named else None


def _type_hints(config_class: type) -> Dict[str, Any]:
    try:
        return get_type_hints(config_class, include_extras=True)
    except Exception:  # a forward reference tyro resolves its own way: the fields are read without their marks
        return {}


def _suppressed(hint) -> bool:
    import tyro

    return get_origin(hint) is Annotated and any(mark is tyro.conf.Suppress for mark in get_args(hint)[1:])


def _subcommand_types(hint) -> Dict[str, type]:
    """The subcommands tyro makes of a field's type (a Union of `tyro.conf.subcommand`-named types) by name."""
    while get_origin(hint) is Annotated:
        hint = get_args(hint)[0]
    if get_origin(hint) is not Union:
        return {}
    named = {}
    for member in get_args(hint):
        marks = get_args(member)[1:] if get_origin(member) is Annotated else ()
        for mark in marks:
            if type(mark).__name__ == "_SubcommandConfig" and getattr(mark, "name", None):
                named[mark.name] = get_args(member)[0]
    return named


def _default_instance(config_class: type):
    try:
        return config_class()
    except Exception:  # a subcommand without defaults for all its fields: its options are not listed
        return None


def bare(flag: str) -> str:
    """A flag without the subcommand it follows."""
    return flag.rpartition(" ")[2]


def flags_of(config) -> List[str]:
    """The flags tyro derives from a config: each field by its dotted path, `_` written `-`, an option of a
    subcommand after it (`nerfstudio-data --data`)."""
    return CommandLine.of(config).flags
