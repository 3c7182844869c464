"""Validate documents against the JSON schemas shipped in ``facetsynth/schemas``."""

from __future__ import annotations

import json
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema

from .errors import EXCERPT_CHARS, InputError


@cache
def schema(name: str) -> dict[str, Any]:
    """A packaged JSON schema by file name, e.g. ``capture_manifest.schema.json``."""
    return json.loads(resources.files("facetsynth").joinpath("schemas", name).read_text())


def validate(document: Any, schema_name: str, path: str | Path | None, what: str) -> None:
    """Raise InputError naming the file and the first offending key."""
    validator = jsonschema.Draft202012Validator(schema(schema_name))
    errors = sorted(validator.iter_errors(document), key=lambda e: [str(p) for p in e.absolute_path])
    if errors:
        err = errors[0]
        where = "/".join(str(p) for p in err.absolute_path) or "(top level)"
        more = f" (and {len(errors) - 1} more problem(s))" if len(errors) > 1 else ""
        raise InputError(path, f"invalid {what} at '{where}': {_bounded(err)}{more}")


def _bounded(err: jsonschema.ValidationError) -> str:
    """The error's message with the offending value quoted by at most EXCERPT_CHARS characters of its repr
    (jsonschema quotes it whole: a file that is not the document expected, e.g. /etc/passwd read as a
    scene, would be printed; issue 32)."""
    message, shown = err.message, repr(err.instance)
    if len(shown) > EXCERPT_CHARS:
        message = message.replace(shown, shown[:EXCERPT_CHARS] + "...")
    return message if len(message) <= 4 * EXCERPT_CHARS else message[:4 * EXCERPT_CHARS] + "..."
