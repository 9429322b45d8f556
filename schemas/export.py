"""Write a JSON Schema per message into ``schemas/json/`` (``python -m schemas.export``).

Clients in other languages decode the msgpack payloads with these. msgspec describes ``bytes``
fields as base64 strings, which is how they look in JSON; on the wire they are msgpack ``bin``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import msgspec

from schemas.codec import MESSAGE_TYPES
from schemas.keys import KEY_TEMPLATES
from schemas.types import SCHEMA_VERSION

JSON_DIR = Path(__file__).resolve().parent / "json"

def schema_of(name: str) -> dict[str, object]:
    schema = msgspec.json.schema(MESSAGE_TYPES[name])
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"mrslam/{name}/v{SCHEMA_VERSION}",
        "description": f"{name} message, msgpack-encoded on key {KEY_TEMPLATES[name]}; "
                       "bytes fields are msgpack bin (raw little-endian arrays).",
        "x-mrslam-key": KEY_TEMPLATES[name],
        "x-mrslam-schema-version": SCHEMA_VERSION,
        **schema,
    }


def render_all() -> dict[str, str]:
    """File name -> JSON text for every message type."""
    return {f"{name}.json": json.dumps(schema_of(name), indent=2, sort_keys=True) + "\n"
            for name in sorted(MESSAGE_TYPES)}


def main() -> int:
    JSON_DIR.mkdir(exist_ok=True)
    files = render_all()
    for stale in JSON_DIR.glob("*.json"):
        if stale.name not in files:
            stale.unlink()
    for fname, text in files.items():
        (JSON_DIR / fname).write_text(text)
    print(f"wrote {len(files)} schemas to {JSON_DIR}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
