"""The configuration reference, ``docs/configuration.md``, generated from the config itself.

Every key, its default and its description come from ``app/config.py`` (:func:`describe`,
the same descriptions ``midair config`` prints as YAML comments), so the page cannot drift
from the code; ``tests/test_docs.py`` checks that the committed page is the generated one.
Regenerate with::

    python -m app.tools.configdoc > docs/configuration.md
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

import yaml

from app.config import Config, describe, explain

COMMAND = "python -m app.tools.configdoc > docs/configuration.md"

_INTRO = f"""\
# Configuration

<!-- Generated from app/config.py by `{COMMAND}`: do not edit by hand. -->

Every threshold and setting of midair, with its unit. `config.yaml` at the top of the
repository is exactly the built-in default (a test keeps the two identical); `midair config`
prints the same as commented YAML (`midair config > my.yaml` to start tuning), and every
command takes `--config FILE`. Keys left out of a file keep their defaults, so a tuning file
can hold only what it changes.

The file loads into frozen dataclasses and is checked at start: an unknown key, a wrong type
or a value outside the rule in the *allowed* column stops the program with exit code 2 and a
message naming the key, such as

    midair: error: perception.recognition.area_px = -3: must be > 0

A few rules tie keys together and are checked too (for example `decision.emergency_m` must
be below the avoidance distance, `decision.evade_speed_mps` at most `decision.max_speed_mps`,
`perception.detection.lk_pyramid_levels` what a `window_px + lk_search_px` crop can hold).
What the measured defaults are based on: [measurements.md](measurements.md).
"""


def _value(value: Any) -> str:
    """A default as YAML writes it (the form ``config.yaml`` and ``midair config`` use)."""
    if isinstance(value, tuple):
        value = list(value)
    text = yaml.safe_dump(value, default_flow_style=True).strip()
    return text.removesuffix("...").strip()


def _cell(text: str) -> str:
    """Text safe inside one markdown table cell."""
    return " ".join(text.split()).replace("|", "\\|")


def _allowed(meta: Any) -> str:
    """The validation rule of one field, as the error message states it."""
    rules: list[str] = []
    for key, sign in (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤")):
        if meta.get(key) is not None:
            rules.append(f"{sign} {meta[key]:g}")
    if meta.get("choices"):
        rules.append(", ".join(f"`{c}`" for c in meta["choices"]))
    if meta.get("odd"):
        rules.append("odd")
    return ", ".join(rules)


def _doc(obj: Any) -> str:
    """A config section's description: its class docstring as one paragraph."""
    return " ".join((type(obj).__doc__ or "").split())


def _section(obj: Any, prefix: str, level: int, out: list[str]) -> None:
    """One section per config dataclass: its own keys in a table, then its sub-sections."""
    name = prefix.removesuffix(".")
    out.append("")
    out.append(f"{'#' * level} {name}")
    doc = _doc(obj)
    if doc:
        out.append("")
        out.append(doc)
    fields = {f.name: f for f in dataclasses.fields(obj)}
    own = [(key, value, text) for key, value, text in describe(obj, prefix=prefix)
           if "." not in key.removeprefix(prefix)]
    if own:
        out.append("")
        out.append("| key | default | allowed | description |")
        out.append("|---|---|---|---|")
        for key, value, text in own:
            meta = fields[key.removeprefix(prefix)].metadata
            out.append(f"| `{key}` | `{_cell(_value(value))}` | {_cell(_allowed(meta))} | "
                       f"{_cell(text)} |")
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            _section(value, f"{prefix}{f.name}.", min(level + 1, 4), out)


def render(cfg: Config | None = None) -> str:
    """The whole configuration reference as markdown."""
    cfg = Config() if cfg is None else cfg
    out = [_INTRO.rstrip("\n")]
    out.append("")
    out.append("Sections: " + ", ".join(
        f"[{f.name}](#{f.name})" for f in dataclasses.fields(cfg)) + ".")
    for f in dataclasses.fields(cfg):
        _section(getattr(cfg, f.name), f"{f.name}.", 2, out)
    out.append("")
    out.append("## How the decision thresholds follow from eq. 4.3")
    out.append("")
    out.append("`midair config --explain` with these defaults:")
    out.append("")
    out.extend("    " + line if line else "" for line in explain(cfg).splitlines())
    return "\n".join(out) + "\n"


def main() -> int:
    """Print the reference: ``python -m app.tools.configdoc > docs/configuration.md``."""
    text = render()
    buffer = getattr(sys.stdout, "buffer", None)
    if buffer is not None:  # UTF-8 whatever the locale says
        buffer.write(text.encode("utf-8"))
        buffer.flush()
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
