"""``scripts/python_tool config_reference``: docs/configuration.md from the configuration classes
themselves -- every key, its default and what it is (with its unit), taken from the code, where
each is written once. ``--check`` says whether the page is current (a test runs it)."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import io
import json
import os
import sys
import tokenize

from ..markers import MarkerConfig
from ..ros.params import ClientNodeParams, ServerNodeParams
from ..team.config import ServerConfig
from ..uplink.config import UplinkConfig
from ..vo.config import VoConfig
from .paths import REPO as _REPO

PAGE = os.path.join(_REPO, "docs", "configuration.md")
# Where each configuration is given: (heading, how it is given, section key, class)
SOURCES = (
    ("config/client.yaml", "client.launch `config:=FILE`", "vo", VoConfig),
    ("config/client.yaml", "client.launch `config:=FILE`", "uplink", UplinkConfig),
    ("config/client.yaml", "client.launch `config:=FILE`", "markers", MarkerConfig),
    ("config/server.yaml", "server.launch `config:=FILE`", "server", ServerConfig),
    ("client node parameters", "client.launch arguments", "~", ClientNodeParams),
    ("server node parameters", "server.launch arguments", "~", ServerNodeParams),
)


def field_notes(cls: type) -> dict[str, str]:
    """Each field's comment in the class source: the comment lines just above it and the one
    after it on its line."""
    notes: dict[str, str] = {}
    above: list[str] = []
    group = ""  # the first of a run of fields (no blank line) under one comment, which tells all
    for indent, code, comment in _lines(inspect.getsource(cls)):
        if indent != 4:
            above, group = ([] if code else above), ("" if not code and not comment else group)
            continue
        if code.startswith("def "):
            break
        if not code:
            above = above + [comment] if comment else []
            continue
        name = code.split(":", 1)[0].strip()
        if ":" in code and name.isidentifier():
            if above:
                group = name
            note = " ".join(above + ([comment] if comment else [])).strip()
            notes[name] = note or (f"(as `{group}` above)" if group else "")
        above = []
    return notes


def _lines(source: str):
    """(indent, code, comment) per physical line of ``source``."""
    comments: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = tok.string.lstrip("#").strip()
    for number, line in enumerate(source.splitlines(), 1):
        comment = comments.get(number, "")
        code = line.split("#", 1)[0].rstrip() if comment else line.rstrip()
        yield len(line) - len(line.lstrip()), code.strip(), comment


def _default(value) -> str:
    if isinstance(value, (dict, list, bool)):
        return f"`{json.dumps(value)}`"
    if isinstance(value, str):
        return f'`"{value}"`'
    return f"`{value}`"


def class_doc(cls: type) -> str:
    """A class's docstring's first paragraph on one line ('' for a dataclass without one)."""
    doc = cls.__doc__ or ""
    if doc.startswith(cls.__name__ + "("):  # the docstring dataclass writes itself
        return ""
    return inspect.cleandoc(doc).split("\n\n")[0].replace("\n", " ")


def _rows(cls: type, obj, prefix: str) -> list[tuple[str, str, str]]:
    notes = field_notes(cls)
    rows, nested = [], []
    for f in dataclasses.fields(cls):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            nested.append((f.name, value))
            continue
        rows.append((prefix + f.name, _default(value), notes.get(f.name, "")))
    for name, value in nested:
        rows.append((prefix + name, "", f"**{class_doc(type(value)) or name}**"))
        rows += _rows(type(value), value, f"{prefix}{name}.")
    return rows


def render() -> str:
    out = [
        "# Configuration",
        "",
        "Every key of coop_slam's configuration, its default and what it is, generated from the",
        "configuration classes (`scripts/python_tool config_reference`; a test keeps this page",
        "current). `config/client.yaml` and `config/server.yaml` hold only what differs from these",
        "defaults; a key can also be given as a private ROS parameter of the node, nested like the",
        "file (`~vo/keyframes/ref_ratio`,",
        '`<rosparam param="rendezvous">{window_s: 3.0}</rosparam>`),',
        "and changes that key only. Unknown keys and values of the wrong type are refused by name.",
        "",
    ]
    for heading, given, section, cls in SOURCES:
        title = f"`{section}`" if section != "~" else "private parameters"
        out += [f"## {heading}: {title} ({cls.__module__}.{cls.__name__})", ""]
        out += [class_doc(cls), "", given, ""]
        out += ["| key | default | what |", "| --- | --- | --- |"]
        prefix = "" if section == "~" else f"{section}."
        for key, default, note in _rows(cls, cls(), prefix):
            out.append(f"| `{key}` | {default} | {note.replace('|', '/')} |")
        out.append("")
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/python_tool config_reference", description=__doc__)
    p.add_argument("--check", action="store_true", help="only say whether the page is current")
    args = p.parse_args(argv)
    text = render()
    current = open(PAGE, encoding="utf-8").read() if os.path.isfile(PAGE) else ""
    if args.check:
        if current != text:
            print(
                f"[config_reference] {PAGE} is out of date: run scripts/python_tool "
                "config_reference"
            )
            return 1
        print(f"[config_reference] {PAGE} is current")
        return 0
    with open(PAGE, "w", encoding="utf-8") as fh:
        fh.write(text)
    print(f"[config_reference] wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
