"""Spoolman (github.com/Donkie/Spoolman) spool extra field holding the fitted pressure advance.

Spoolman's rules, read at commit a9e50559bb11604808c34bd3f78734e8d2ca942c (v0.26.1+):

* a field is defined once per entity type with ``POST /api/v1/field/spool/{key}``
  (spoolman/api/v1/field.py), body ``ExtraFieldParameters`` (spoolman/extra_field_registry.py):
  ``name`` 1-128 chars, ``field_type`` ("float" here), ``unit`` 1-16 chars or absent,
  ``order``; the key is a path parameter with ``min_length=1, max_length=64,
  pattern="^[a-z0-9_]+$"`` (the same on ``ExtraField.key``); a field's type cannot be changed;
* a spool's ``extra`` (spoolman/api/v1/spool.py, ``SpoolParameters.extra: dict[str, str |
  None]``) maps keys to JSON-encoded strings; ``validate_extra_field_value`` json.loads the
  string and, for a float field, wants an int or float that is not a bool;
* ``PATCH /api/v1/spool/{id}`` merges ``extra`` per key (spoolman/database/spool.py
  ``update``): the spool's other extra fields are kept.

Nothing here talks to the network: calib prints the bodies and the curl lines.
"""
from __future__ import annotations

import json
import re

from calib.errors import UserError

#: the key rule of Spoolman's field endpoints and ExtraField.key
KEY_RE = re.compile(r"[a-z0-9_]{1,64}")
DEFAULT_KEY = "pressure_advance"
DEFAULT_URL = "http://localhost:7912"        # Spoolman's default port
FIELD_NAME = "Pressure advance"
FIELD_UNIT = "s"


def check_key(key: str) -> str:
    """``key`` if Spoolman accepts it as an extra-field key, else UserError (one line)."""
    if not isinstance(key, str) or not KEY_RE.fullmatch(key):
        raise UserError(f"--field-key {key!r} is not a Spoolman extra-field key: it must be 1-64 "
                        "characters of a-z, 0-9 and _ (Spoolman's rule ^[a-z0-9_]+$)")
    return key


def encode_float(k: float) -> str:
    """The extra-field value of a float field: the JSON text of the number (4 decimals, the
    same digits as the firmware targets print)."""
    text = f"{float(k):.4f}"
    if text.startswith("-0.0000"):
        text = "0.0000"
    return text


def field_definition() -> dict:
    """Body of ``POST /api/v1/field/spool/{key}``, created once per Spoolman."""
    return {"name": FIELD_NAME, "field_type": "float", "unit": FIELD_UNIT, "order": 0}


def patch_body(k: float, key: str = DEFAULT_KEY) -> dict:
    """Body of ``PATCH /api/v1/spool/{id}`` that sets the spool's field ``key`` to ``k``."""
    return {"extra": {check_key(key): encode_float(k)}}


def curl_lines(k: float, key: str = DEFAULT_KEY, spool_id: int | None = None,
               url: str = DEFAULT_URL) -> tuple[str, str]:
    """(the field definition, once; the spool update) as curl command lines."""
    check_key(key)
    sid = str(spool_id) if spool_id is not None else "<SPOOL_ID>"
    hdr = "-H 'Content-Type: application/json'"
    define = (f"curl -X POST {url}/api/v1/field/spool/{key} {hdr} "
              f"-d '{json.dumps(field_definition())}'")
    patch = (f"curl -X PATCH {url}/api/v1/spool/{sid} {hdr} "
             f"-d '{json.dumps(patch_body(k, key))}'")
    return define, patch
