"""Scenario edits sent as JSON: the ``[[actor]]`` and ``[[insert]]`` tables of a scenario
file (docs/simulation.md), as a JSON object ``{"actor": [...], "insert": [...]}``, turned
into the TOML text the simulation plugin's parser reads, so both forms are checked by the
same code (omnire_sim.scenario.parse_scenario)."""
from __future__ import annotations

import json
import math
from pathlib import Path

from omnire_serve.errors import RequestError
from omnire_sim import Scenario, ScenarioError, parse_scenario

TABLES = ("actor", "insert")


def _value(v, field: str) -> str:
    """A TOML inline value for the JSON value ``v``."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise RequestError(field, "non-finite number (NaN or infinity)")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string (same escapes)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x, f"{field}.{i}") for i, x in enumerate(v)) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_value(x, f'{field}.{k}')}" for k, x in v.items()) + "}"
    raise RequestError(field, f"{v!r}: expected a string, number, boolean, list or object (null is not allowed)")


def tables_to_toml(tables) -> str:
    """TOML text of ``{"actor": [...], "insert": [...]}``."""
    if not isinstance(tables, dict):
        raise RequestError("", "expected a JSON object {\"actor\": [...], \"insert\": [...]}")
    unknown = sorted(set(tables) - set(TABLES))
    if unknown:
        raise RequestError(unknown[0], f"unknown table; expected {list(TABLES)}")
    lines = []
    for name in TABLES:
        items = tables.get(name, [])
        if not isinstance(items, list):
            raise RequestError(name, "expected a list of tables (objects)")
        for i, item in enumerate(items):
            if not isinstance(item, dict):
                raise RequestError(f"{name}.{i}", "expected an object (one table)")
            lines.append(f"[[{name}]]")
            lines += [f"{json.dumps(str(k))} = {_value(v, f'{name}.{i}.{k}')}" for k, v in item.items()]
    return "\n".join(lines) + "\n"


def parse_tables(tables, base_dir: Path) -> Scenario:
    """The scenario of the JSON tables (relative paths resolved against ``base_dir``)."""
    text = tables_to_toml(tables)
    try:
        return parse_scenario(text, "scenario", base_dir)
    except ScenarioError as exc:
        raise RequestError(field_of_error(str(exc)), str(exc)) from None


def field_of_error(message: str) -> str:
    """``actor.0.track`` from a scenario error ``scenario line 3, [[actor]] #1, field 'track': ...``."""
    head = message.split(": ", 1)[0]
    table, field = "", ""
    for part in head.split(", "):
        if part.startswith("[[") and "#" in part:
            name, number = part[2:].split("]]")[0], part.split("#")[1]
            table = f"{name}.{int(number) - 1}" if number.strip().isdigit() else name
        elif part.startswith("field '"):
            field = part[len("field '"):-1]
    return ".".join(p for p in (table, field) if p) or "scenario"
