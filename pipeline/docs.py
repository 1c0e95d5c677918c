"""Reference documentation generated from the stage declarations, so the
README's tables of config keys can never drift from the code
(`worldbake describe`; a test checks the README holds the current text)."""
from __future__ import annotations

import typing

from .config import TOP_LEVEL_KEYS, describe_allowed
from .contract import Stage


def _type_name(annotation) -> str:
    if typing.get_origin(annotation) is typing.Literal:
        return " \\| ".join(f'"{a}"' for a in typing.get_args(annotation))
    text = getattr(annotation, "__name__", None) or str(annotation)
    return text.replace("typing.", "").replace("NoneType", "None").replace("|", "\\|")


def describe(stages: dict[str, Stage]) -> str:
    lines = ["Top-level keys:", "", "| key | meaning |", "|---|---|"]
    lines += [f"| `{k}` | {v} |" for k, v in TOP_LEVEL_KEYS.items()]
    for stage in stages.values():
        lines += ["", f"### `[{stage.name}]` (version {stage.version})", "", stage.description, ""]
        if stage.inputs:
            lines.append("Reads: " + "; ".join(f"`{i.role}` from " + " or ".join(f"`{a}`" for a in i.one_of) for i in stage.inputs) + ".")
        lines.append("Writes: " + "; ".join(f"`{a.name}` (`{a.file}`{', ' + a.units if a.units else ''})" for a in stage.outputs) + ".")
        lines += ["", "| key | type | default | allowed, units, meaning |", "|---|---|---|---|"]
        for name, field in stage.params.model_fields.items():
            default = field.get_default(call_default_factory=True)
            if isinstance(default, dict):  # tables: name the keys, their contents are documented by the stage
                shown = "tables " + ", ".join(f"`{k}`" for k in default) if default else "`{}`"
            else:
                shown = f"`{default!r}`".replace("'", '"')
            lines.append(f"| `{name}` | {_type_name(field.annotation)} | {shown} | {describe_allowed(field).replace('|', '/')} |")
    return "\n".join(lines) + "\n"
