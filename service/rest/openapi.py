"""The OpenAPI document, exact for the server that serves it.

FastAPI's generated document describes the bodies by their pydantic types; what the server accepts depends
also on the loaded models (goal ids and names, action modes, observation shapes) and on the auth setting. This
module rewrites the request bodies from the loaded models, so that a body the schema admits is accepted and one
it does not is refused (schemathesis checks both, `tests/service/test_schemathesis.py`), and declares bearer
auth as a security scheme only when the server requires a token.

What JSON Schema cannot say, and how the schema deals with it:
- An observation is checked against the model of the session named in the path, which the body does not
  name: with several models loaded the schema admits the observation of any of them.
- Numbers: observation values and targets must be within +-1e9 (`observations.MAX_ABS_VALUE`), a bound both
  sides compare exactly (a bound at the float64 maximum is not: a larger integer literal rounds to it).
- Tensor bytes: a pattern over base64 cannot check that float or 64-bit integer values are finite and in range.
  The schema lists the tensor dtypes whose every value is acceptable (8- and 16-bit integers; `uint8` for
  images); the server also accepts the other numeric dtypes when their values are in range.
- The body size limit (`--max-request-bytes`) is in the description and in the 413 answers; `schemathesis.toml`
  counts 413 as a refusal.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from gmt.model.checkpoint import VERSION_PATTERN
from gmt.model.engine import MAX_BLEND_STEPS
from gmt.service.core import Core
from gmt.service.examples import Example
from gmt.service.ids import SESSION_ID_PATTERN
from gmt.service.observations import MAX_ABS_VALUE
from gmt.service.records import INFO_KEY, MAX_INFO_KEYS, MAX_REPORTED
from gmt.service.rest import schemas as S
from gmt.service.views import MAX_ACT_ITEMS, ModelView

BEARER = "bearerAuth"
ADMIN = "adminAuth"
MANAGEMENT_TAG = "model management"  # the tag of `models_admin`'s routes
OPEN_OPERATIONS = {("/healthz", "get"), ("/readyz", "get")}  # answered without a token
VECTOR_TENSOR_DTYPES = ("uint8", "int8", "uint16", "int16")  # every value of these is within +-MAX_ABS_VALUE
B64 = "[A-Za-z0-9+/]"


def build(app: FastAPI, core: Core | None) -> dict:
    """The document for `app` over `core`'s loaded models and auth setting."""
    settings = app.settings
    doc = get_openapi(
        title=app.title,
        version=app.version,
        description=app.description
        + f"\n\nRequest bodies are limited to {settings.max_request_bytes} bytes (413 payload_too_large)"
        + " and are JSON: `Content-Type: application/json` (415 unsupported_media_type otherwise, without one too)."
        + ' Errors are `{"error": {"code", "message"}}`.',
        routes=app.routes,
    )
    models = core.list_models() if core is not None and core.started else []
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):  # FastAPI's 422, which this server never answers
        schemas.pop(name, None)
    for item in doc["paths"].values():
        for op in item.values():
            op.get("responses", {}).pop("422", None)
            if "requestBody" in op:  # `media.require_json` / `FastAct`
                op["responses"]["415"] = {
                    "description": "The body's Content-Type is not application/json (or absent)",
                    "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}},
                }
    # The act routes read raw bytes and refer to their bodies' components in `openapi_extra`, from which FastAPI
    # collects none: they are added here (`_exact_bodies` narrows them to the loaded models).
    for model in (S.Act, S.ActMany):
        schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, d in schema.pop("$defs", {}).items():
            schemas.setdefault(name, d)
        schemas.setdefault(model.__name__, schema)
    if models:
        _exact_bodies(doc, schemas, models)
        _act_examples(doc, models, getattr(app.state, "examples", {}))
    _version_paths(doc)
    _bearer_auth(doc, bool(settings.keys), settings.admin_token is not None)
    return doc


def _version_paths(doc: dict) -> None:
    """Give every `{version}` path parameter the pattern the server checks (`core.check_version`)."""
    for item in doc["paths"].values():
        for op in item.values():
            for p in op.get("parameters", []):
                if p["in"] == "path" and p["name"] == "version":
                    p["schema"] = {**p["schema"], "pattern": f"^{VERSION_PATTERN.pattern}$", "maxLength": 64}


# ----- request bodies -----------------------------------------------------------------------------------------
def _body(doc: dict, path: str, method: str) -> dict:
    return doc["paths"][path][method]["requestBody"]["content"]["application/json"]


def _exact_bodies(doc: dict, schemas: dict, models: list[ModelView]) -> None:
    described = {n: schemas.get(n, {}).get("properties", {}) for n in ("CreateSession", "SetGoal", "Act")}
    observation = _any_of([observation_schema(m) for m in models])
    schemas["Observation"] = {
        **observation,
        "description": "The observation, in the shape of the model's observation space: nested lists of numbers "
        "within +-1e9 (integers 0..255 for images), or a base64 raw array "
        "`{data, dtype, shape}`. With several models loaded, the session's model decides which shape applies.",
    }
    schemas["CreateSession"] = _create_session(models, described["CreateSession"])
    schemas["SetGoal"] = _set_goal(models, described["SetGoal"])
    schemas["ResetSession"] = _reset(models)
    schemas["Act"] = {
        "title": "Act",
        "description": "`POST /sessions/{id}/act`: one observation.",
        "type": "object",
        "properties": {
            "observation": {"$ref": "#/components/schemas/Observation"},
            "step": {
                **_nullable(_STEP),
                "description": described["Act"].get("step", {}).get("description", ""),
            },
            **_report(described["Act"]),
        },
        "required": ["observation"],
    }
    # POST /act: a bad observation, tensor or session fails its item alone (in the answer), so the schema of an
    # item's observation is the envelope the whole call is refused without.
    schemas["Tensor"] = {
        "title": "Tensor",
        "description": "A raw little-endian array, base64-encoded (images).",
        "type": "object",
        "properties": {
            "data": {"type": "string", "description": "Standard base64 of the array's bytes."},
            "dtype": {"type": "string", "description": "NumPy dtype name, e.g. uint8 or float32."},
            "shape": {"type": "array", "items": {"type": "integer"}},
        },
        "required": ["data", "dtype", "shape"],
    }
    schemas["ActItem"] = {
        "title": "ActItem",
        "description": "One item of `POST /act`: a session and its observation (as in `POST "
        "/sessions/{id}/act`; a wrong one fails this item alone).",
        "type": "object",
        "properties": {
            "session_id": {"type": "string"},
            "observation": {"anyOf": [{"type": "array"}, {"$ref": "#/components/schemas/Tensor"}]},
            "step": _nullable(_STEP),
            **_report(described["Act"], exact=False),
        },
        "required": ["session_id", "observation"],
    }
    schemas["ActMany"] = {
        "title": "ActMany",
        "description": "`POST /act`: one step for each of many sessions, in one forward pass.",
        "type": "object",
        "properties": {
            "requests": {
                "type": "array",
                "items": {"$ref": "#/components/schemas/ActItem"},
                "maxItems": MAX_ACT_ITEMS,
            }
        },
        "required": ["requests"],
    }


def _act_examples(doc: dict, models: list[ModelView], examples: dict[str, Example]) -> None:
    """Each model's example observation (`gmt.service.examples`) as an example body of the act operations."""
    shown = [(m.name, examples[m.name]) for m in models if m.name in examples]
    shown = [(name, e) for name, e in shown if e.observation is not None]  # images: no frame in the document
    if not shown:
        return
    _body(doc, "/sessions/{session_id}/act", "post")["examples"] = {
        name: {"summary": f"{name}: {e.description}", "value": {"observation": e.observation}}
        for name, e in shown
    }
    _body(doc, "/act", "post")["examples"] = {
        name: {
            "summary": f"{name}: {e.description}",
            "value": {
                "requests": [{"session_id": f"<id of a session on {name}>", "observation": e.observation}]
            },
        }
        for name, e in shown
    }


_STEP = {"type": "integer", "minimum": 0}
_REPORTED = {"type": "number", "minimum": -MAX_REPORTED, "maximum": MAX_REPORTED}


def _report(described: dict, exact: bool = True) -> dict:
    """The act's optional report on the previous action: `records.check_report`'s rules when `exact`, else only
    the types (an item of `POST /act` whose report breaks a rule fails alone, not the call)."""
    key = INFO_KEY.pattern
    number = _REPORTED if exact else {"type": "number"}
    info = {"type": "object", "additionalProperties": number}
    if exact:
        info |= {"propertyNames": {"pattern": f"^{key}$"}, "maxProperties": MAX_INFO_KEYS}
    return {
        "reward": {**_nullable(number), "description": described.get("reward", {}).get("description", "")},
        "terminated": {
            **_nullable({"type": "boolean"}),
            "description": described.get("terminated", {}).get("description", ""),
        },
        "truncated": {
            **_nullable({"type": "boolean"}),
            "description": described.get("truncated", {}).get("description", ""),
        },
        "info": {**_nullable(info), "description": described.get("info", {}).get("description", "")},
    }


_TARGET = {"type": "number", "minimum": -MAX_ABS_VALUE, "maximum": MAX_ABS_VALUE}


def _nullable(schema: dict) -> dict:
    return {"anyOf": [schema, {"type": "null"}]}


def _any_of(schemas: list[dict]) -> dict:
    unique: list[dict] = []
    for s in schemas:
        if s not in unique:
            unique.append(s)
    return unique[0] if len(unique) == 1 else {"anyOf": unique}


def _goal(models: list[ModelView]) -> dict:
    ids = sorted({g.id for m in models for g in m.goals})
    names = sorted({g.name for m in models for g in m.goals})
    return {
        "anyOf": [{"type": "integer", "enum": ids}, {"type": "string", "enum": names}, {"type": "null"}],
        "description": "Goal id or goal name (`GET /models/{name}` lists them).",
    }


def _exactly_one_goal() -> list[dict]:
    """Exactly one of goal (an id or a name) and target is given (not null)."""
    return [
        {"required": ["goal"], "properties": {"goal": {"not": {"type": "null"}}}},
        {"required": ["target"], "properties": {"target": {"type": "number"}}},
    ]


def _target(described: dict | None = None) -> dict:
    d = (described or {}).get("target", {}).get("description")
    return {
        **_nullable(_TARGET),
        "description": d or "Target statistic value: the nearest goal mean is chosen.",
    }


def _create_session(models: list[ModelView], described: dict) -> dict:
    def one(m: ModelView, required: bool) -> dict:
        # With one model loaded, an empty or missing name means that model (as an unset gRPC field does).
        model = {"const": m.name} if required else {"anyOf": [{"enum": [m.name, ""]}, {"type": "null"}]}
        return {
            "type": "object",
            "properties": {
                "model": {**model, "description": "Model name; may be omitted when one model is loaded."},
                "goal": _goal([m]),
                "target": _target(described),
                "seed": {
                    **_nullable({"type": "integer", "minimum": 0, "maximum": 2**63 - 1}),
                    "description": described.get("seed", {}).get("description", ""),
                },
                "action_mode": {
                    **_nullable({"type": "string", "enum": list(m.action_modes)}),
                    "description": "One of the model's action modes (`GET /models/{name}`); the first is the "
                    "default.",
                },
                "session_id": {
                    **_nullable({"type": "string", "pattern": rf"^(?!\.\.?$){SESSION_ID_PATTERN}$"}),
                    "description": described.get("session_id", {}).get("description", ""),
                },
                "version": {  # any name: versions are loaded and unloaded after this document is built
                    **_nullable({"type": "string", "pattern": f"^{VERSION_PATTERN.pattern}$"}),
                    "description": described.get("version", {}).get("description", ""),
                },
                "record": {
                    **_nullable({"type": "boolean"}),
                    "description": described.get("record", {}).get("description", ""),
                },
            },
            **({"required": ["model"]} if required else {}),
            "oneOf": _exactly_one_goal(),
        }

    body = one(models[0], False) if len(models) == 1 else {"oneOf": [one(m, True) for m in models]}
    return {
        "title": "CreateSession",
        "description": "`POST /sessions`: a model and exactly one of a goal (id or name) and a target value.",
        **body,
    }


def _set_goal(models: list[ModelView], described: dict) -> dict:
    return {
        "title": "SetGoal",
        "description": "`PUT /sessions/{id}/goal`: exactly one of a goal (id or name of the session's model) and "
        "a target value.",
        "type": "object",
        "properties": {
            "goal": _goal(models),
            "target": _target(described),
            "blend_steps": {
                "type": "integer",
                "minimum": 0,
                "maximum": MAX_BLEND_STEPS,
                "default": 0,
                "description": described.get("blend_steps", {}).get("description", ""),
            },
        },
        "oneOf": _exactly_one_goal(),
    }


def _reset(models: list[ModelView]) -> dict:
    return {
        "title": "ResetSession",
        "description": "`POST /sessions/{id}/reset`: optionally a new goal (an id or a name, or a target "
        "value, not both).",
        "type": "object",
        "properties": {"goal": _goal(models), "target": _target()},
        "not": {
            "required": ["goal", "target"],
            "properties": {"goal": {"not": {"type": "null"}}, "target": {"type": "number"}},
        },
    }


def observation_schema(m: ModelView) -> dict:
    """What the server accepts as an observation for model `m` (Box spaces; anything else is not narrowed)."""
    space = m.observation_space
    if space.get("type") != "box":
        return {"anyOf": [{"type": "array"}, {"$ref": "#/components/schemas/Tensor"}]}
    shape = [int(s) for s in space["shape"]]
    image = space.get("dtype") == "uint8"
    if image:
        leaf: dict[str, Any] = {"type": "integer", "minimum": 0, "maximum": 255}
        dtypes: tuple[str, ...] = ("uint8",)
    else:
        leaf = {"type": "number", "minimum": -MAX_ABS_VALUE, "maximum": MAX_ABS_VALUE}
        dtypes = VECTOR_TENSOR_DTYPES
    # A (1, H, W) image may also come as (H, W).
    shapes = [shape] + ([shape[1:]] if len(shape) == 3 and shape[0] == 1 else [])
    forms = [_nested(leaf, s) for s in shapes]
    forms += [_tensor(d, s) for s in shapes for d in dtypes]
    return {"anyOf": forms}


def _nested(leaf: dict, shape: list[int]) -> dict:
    schema = leaf
    for n in reversed(shape):
        schema = {"type": "array", "items": schema, "minItems": n, "maxItems": n}
    return schema


def _tensor(dtype: str, shape: list[int]) -> dict:
    n = math.prod(shape) * np.dtype(dtype).itemsize
    full, rest = divmod(n, 3)
    tail = {0: "", 1: f"{B64}{{2}}==", 2: f"{B64}{{3}}="}[rest]
    length = 4 * (full + (rest > 0))
    return {
        "type": "object",
        "properties": {
            "data": {
                "type": "string",
                "pattern": f"^(?:{B64}{{4}}){{{full}}}{tail}$",
                "minLength": length,
                "maxLength": length,
                "description": f"Standard base64 of {n} bytes.",
            },
            "dtype": {"const": dtype},
            "shape": {"const": shape},
        },
        "required": ["data", "dtype", "shape"],
    }


# ----- auth ---------------------------------------------------------------------------------------------------
def _bearer_auth(doc: dict, token: bool, admin_token: bool) -> None:
    """Declare the bearer schemes the server checks: `--auth-token` on every operation but the health checks,
    `--admin-token` (instead) on model management; each secured operation documents its 401."""
    schemes = {}
    if token:
        schemes[BEARER] = {
            "type": "http",
            "scheme": "bearer",
            "description": "A key of the server (--auth-token, or one of --auth-tokens): `Authorization: Bearer <token>`.",
        }
    if admin_token:
        schemes[ADMIN] = {
            "type": "http",
            "scheme": "bearer",
            "description": "The server's --admin-token, for model management: `Authorization: Bearer <token>`.",
        }
    if not schemes:
        return
    doc["components"]["securitySchemes"] = schemes
    unauthenticated = {
        "description": "Missing or wrong bearer token",
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}},
    }
    for path, item in doc["paths"].items():
        for method, op in item.items():
            managing = MANAGEMENT_TAG in op.get("tags", ())
            scheme = ADMIN if managing and admin_token else BEARER if token else None
            if (path, method) in OPEN_OPERATIONS or scheme is None:
                continue
            op["security"] = [{scheme: []}]
            op.setdefault("responses", {})["401"] = unauthenticated
