"""A cell config's YAML read with the line of every key (``parse_yaml_with_lines``), so each problem
the checks of runtime/config.py find names FILE:LINE; hostile documents (alias bombs, deep nesting,
scalars a tag cannot build) become a ``ConfigError``, never a crash or a hang."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml


class ConfigError(ValueError):
    """Every problem in one config file; ``problems`` are ``FILE:LINE: key: message`` lines."""

    def __init__(self, path: Path | str, problems: list[str]) -> None:
        self.path = Path(path)
        self.problems = list(problems)
        body = "\n".join(f"  {p}" for p in self.problems)
        super().__init__(f"config {self.path}: {len(self.problems)} problem(s)\n{body}")


_NULL_TAG = "tag:yaml.org,2002:null"
_NUMBER_TAGS = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")
# YAML 1.1 (PyYAML) reads a plain 010 as octal 8 and 1:30 as base-60 90: a person means 10 and
# something else; refused, so a bin, a press limit or a time is never silently another number
_SURPRISING_NUMBER = re.compile(r"[-+]?0[0-7_]+|[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?")
_MAX_NODES = 5000  # a cell config has a few hundred; aliases must not expand without bound (each
# scalar costs a ~90 us serialize + safe_load round trip: 20000 made an alias bomb take 1.8 s)


def _to_python(node: yaml.Node, key: str, lines: dict[str, int], budget: list[int] | None = None) -> Any:
    budget = budget if budget is not None else [_MAX_NODES]
    budget[0] -= 1
    if budget[0] < 0:
        raise _TooBig()
    lines[key] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        out: dict[str, Any] = {}
        for k_node, v_node in node.value:
            k = str(yaml.safe_load(yaml.serialize(k_node))) if not isinstance(k_node, yaml.ScalarNode) else k_node.value
            sub = f"{key}.{k}" if key else k
            lines[sub] = k_node.start_mark.line + 1
            if k in out:
                lines.setdefault("__dup__", [])  # type: ignore[arg-type]
                lines["__dup__"].append(sub)  # type: ignore[union-attr]
            out[k] = _to_python(v_node, sub, lines, budget)
            lines[sub] = k_node.start_mark.line + 1
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_to_python(v, f"{key}[{i}]", lines, budget) for i, v in enumerate(node.value)]
    if node.tag == _NULL_TAG:
        # `key:` with nothing after it, `key: null`, `key: ~`: YAML's null, what safe_load gives;
        # serialized alone, an empty scalar is an empty document, which does not load back
        return None
    # a plain scalar YAML resolved to a number, or one tagged a number (`!!int "010"` is 8 too); a
    # quoted scalar without a tag is text
    if node.tag in _NUMBER_TAGS and _SURPRISING_NUMBER.fullmatch(node.value):
        value = yaml.safe_load(yaml.serialize(node))
        decimal = None if ":" in node.value else int(node.value.replace("_", ""), 10)
        if value != decimal:  # 07 is 7 either way
            raise _SurprisingNumber(node.start_mark.line + 1, key or "the document", node.value, value, decimal)
    try:
        return yaml.safe_load(yaml.serialize(node))
    except (yaml.YAMLError, ValueError, TypeError, AttributeError, KeyError, IndexError) as exc:
        # An explicit tag the value does not fit ("!!timestamp x" -> AttributeError, "!!bool maybe"
        # -> KeyError, "!!int ''" -> IndexError inside PyYAML): say where, like every other problem.
        raise _BadScalar(node.start_mark.line + 1, key or "the document", node.tag, exc) from None


def parse_yaml_with_lines(text: str, path: Path) -> tuple[Any, dict[str, int]]:
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except RecursionError:  # thousands of nested [ or {: the composer recurses per level
        raise ConfigError(path, [f"{path}: nested too deeply to be a cell config"]) from None
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: e.g. NUL bytes the reader refuses
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise ConfigError(path, [f"{where}: not valid YAML ({getattr(exc, 'problem', exc)})"]) from None
    lines: dict[str, int] = {}
    if node is None:
        return {}, lines
    try:
        return _to_python(node, "", lines), lines
    except (_TooBig, RecursionError):
        raise ConfigError(path, [f"{path}: too large or self-referencing (YAML aliases); a cell config is "
                                 "a few dozen keys"]) from None
    except _BadScalar as bad:
        line, key, tag, exc = bad.args
        raise ConfigError(path, [f"{path}:{line}: {key}: not valid YAML for tag {tag} "
                                 f"({type(exc).__name__}: {str(exc)[:200]})"]) from None
    except _SurprisingNumber as bad:
        line, key, text, value, decimal = bad.args
        meant = (f"a colon makes it base 60; write {value} if that is meant" if decimal is None
                 else f"a leading 0 makes it octal; write {decimal} if that is meant, or {value}")
        raise ConfigError(path, [f"{path}:{line}: {key}: {text} reads as {value} in YAML ({meant}; quote it "
                                 "only where text is meant)"]) from None
    except yaml.YAMLError as exc:
        raise ConfigError(path, [f"{path}: not valid YAML ({str(exc)[:200]})"]) from None


class _TooBig(Exception):
    pass


class _SurprisingNumber(Exception):
    """(line, key, the text as written, what YAML 1.1 makes of it, its decimal reading or None for
    base 60) of an octal or base-60 number."""


class _BadScalar(Exception):
    """(line, key, tag, the constructor's exception) of a scalar PyYAML could not build."""
