"""VDA 5050 2.0.0 messages against the official JSON schemas in ``schemas/`` (jsonschema, draft 2020-12).

The schema files are the published ones, byte for byte. One repair happens in memory: the
2.0.0 ``factsheet.json`` declares its sections (typeSpecification, physicalParameters, ...)
beside ``properties`` instead of inside it, so a validator would check only that they exist;
they are moved into ``properties`` here so that their contents are checked too. Its
``localizationParameters`` is declared an integer there (an object in the text of the
standard), so this vehicle does not send it.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Any, Dict, List

from robot.base.errors import ConfigError

SCHEMA_DIR = Path(__file__).resolve().parent / "schemas"
SCHEMA_FILES = {"order": "order.schema", "instantActions": "instantActions.schema", "state": "state.schema",
                "connection": "connection.schema", "visualization": "visualization.schema",
                "factsheet": "factsheet.json"}
_META_KEYS = {"$schema", "$id", "title", "description", "required", "subtopic", "type", "properties"}
MAX_PROBLEMS = 5
_PROBLEM_CHARS = 160


def load_schema(topic: str) -> Dict[str, Any]:
    with open(SCHEMA_DIR / SCHEMA_FILES[topic], encoding="utf-8") as f:
        schema = json.load(f)
    if topic == "factsheet":
        schema = dict(schema)
        props = dict(schema.get("properties", {}))
        for key in [k for k in schema if k not in _META_KEYS]:
            props[key] = schema.pop(key)
        schema["properties"] = props
    return schema


@lru_cache(maxsize=None)
def validator(topic: str):
    try:
        import jsonschema
    except ImportError:
        raise ConfigError("fleet: jsonschema is not installed (install the 'fleet' extra: pip install "
                          "'planeloc-robot[fleet]')") from None
    schema = load_schema(topic)
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


def problems(topic: str, message: Any, limit: int = MAX_PROBLEMS) -> List[str]:
    """What is wrong with ``message`` as a ``topic`` message (empty: valid), at most ``limit`` lines."""
    errors = sorted(validator(topic).iter_errors(message), key=lambda e: [str(p) for p in e.absolute_path])
    out = []
    for e in errors[:limit]:
        where = "/".join(str(p) for p in e.absolute_path) or "(message)"
        text = e.message if len(e.message) <= _PROBLEM_CHARS else e.message[:_PROBLEM_CHARS - 3] + "..."
        out.append(f"{where}: {text}")
    return out


__all__ = ["SCHEMA_DIR", "SCHEMA_FILES", "load_schema", "problems", "validator"]
