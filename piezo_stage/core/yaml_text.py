"""Bounded YAML text: the parser every file and message of ours goes through (a model,
a plant, the node parameters, a model message), with no aliases and bounded nesting
and size. Plain PyYAML: no numerical import, so a command that only reads a
configuration (the launcher) pays nothing else for it."""

from __future__ import annotations

import yaml

from piezo_stage.core.errors import ModelError

MAX_YAML_BYTES = 1_000_000  # a model or plant file is a few kB; this is generous


MAX_YAML_DEPTH = 32         # ours nest 5 deep; PyYAML's composer recurses per level


# Aliases are refused (a 1 kB 'billion laughs' document expands to gigabytes; our files
# never need anchors) from the parser's events, before anything is composed.
_FAST_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def parse_yaml(text: str, source: str = "YAML", max_bytes: int = MAX_YAML_BYTES) -> object:
    """Parse bounded YAML text (no aliases, at most max_bytes); ModelError on any
    problem, with where."""
    if len(text) > max_bytes:
        raise ModelError(f"{source}: {len(text)} bytes, more than the {max_bytes} accepted")
    try:
        # the nesting and aliases first, from the parser's events (an iterative state
        # machine): the composer recurses once per level, and 20,000 '[' would exhaust
        # the stack. libyaml's parser when there is one: a model message is then parsed
        # in well under a millisecond, not 5 ms in Python (a feedforward taking a new
        # model while armed must not hold its loop up)
        depth = 0
        for event in yaml.parse(text, Loader=_FAST_LOADER):
            if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
                depth += 1
                if depth > MAX_YAML_DEPTH:
                    mark = event.start_mark
                    raise ModelError(f"{source}: nested deeper than {MAX_YAML_DEPTH} levels "
                                     f"at line {mark.line + 1}")
            elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                depth -= 1
            elif isinstance(event, yaml.AliasEvent):
                raise ModelError(f"{source}: aliases are not accepted at line "
                                 f"{event.start_mark.line + 1}")
        # no aliases, at most MAX_YAML_DEPTH levels: the safe loader composes it as is
        return yaml.load(text, Loader=_FAST_LOADER)  # noqa: S506 - a safe loader
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        why = ("aliases are not accepted" if "aliases" in str(e) else
               f"nested deeper than {MAX_YAML_DEPTH} levels" if "nesting depth" in str(e)
               else "malformed YAML")  # (libyaml's own bound, met before ours)
        raise ModelError(f"{source}: {why}{where}") from None
