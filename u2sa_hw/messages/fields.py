"""Field enumeration (requirement M1) and conversion of messages to/from plain values."""

from __future__ import annotations

from typing import Any

_INTS = {"int8_t", "int16_t", "int32_t", "int64_t", "byte"}
_FLOATS = {"float", "double"}


def _is_lcm(value: Any) -> bool:
    return hasattr(type(value), "_get_packed_fingerprint")


class _Absent(str):
    """The value of a presence-vector field whose bit is clear: ``-``, never 0.

    A ``str`` so that whatever prints, compares or writes the values as JSON keeps working;
    test for it with ``value is ABSENT``.
    """

    __slots__ = ()

    def __reduce__(self) -> str:
        return "ABSENT"


ABSENT = _Absent("-")


def _absent(msg: Any, name: str) -> bool:
    """True when *name* is a presence-vector field of *msg* that the message does not carry."""
    fields = getattr(type(msg), "PRESENCE_FIELDS", ())
    return name in fields and not msg.has(name)


def enumerate_fields(msg: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """``(name, value)`` for every primitive field, nested structs flattened with dots.

    Arrays of primitives come back as one list; arrays of structs as ``name[i].field``.
    A presence-vector field the message does not carry (its bit clear) comes back as
    :data:`ABSENT`, which prints as ``-``: an absent field is never read as 0.
    """
    out: list[tuple[str, Any]] = []
    for name in msg.__slots__:
        value = getattr(msg, name)
        path = f"{prefix}{name}"
        if _absent(msg, name):
            out.append((path, ABSENT))
        elif _is_lcm(value):
            out.extend(enumerate_fields(value, f"{path}."))
        elif isinstance(value, (list, tuple)) and value and _is_lcm(value[0]):
            for i, item in enumerate(value):
                out.extend(enumerate_fields(item, f"{path}[{i}]."))
        elif isinstance(value, (bytes, bytearray)):
            out.append((path, bytes(value).hex()))
        elif isinstance(value, tuple):
            out.append((path, list(value)))
        else:
            out.append((path, value))
    return out


def to_dict(msg: Any) -> dict[str, Any]:
    """A JSON-ready nested dict of the message (bytes as hex), with ``_type``.

    A presence-vector field the message does not carry is None (JSON null), never 0; every
    field keeps its key, so the dict still matches the type's schema (``foxglove.lcm_json``).
    """
    out: dict[str, Any] = {"_type": type(msg).__name__}
    for name in msg.__slots__:
        out[name] = None if _absent(msg, name) else _plain(getattr(msg, name))
    return out


def _plain(value: Any) -> Any:
    if _is_lcm(value):
        return to_dict(value)
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def field_type(msg: Any, path: str) -> tuple[Any, str, str]:
    """Resolve a dotted *path* in *msg*; return ``(owner, attribute, lcm type name)``."""
    owner = msg
    parts = path.split(".")
    for part in parts[:-1]:
        if part not in owner.__slots__:
            raise KeyError(f"{type(owner).__name__} has no field {part!r}")
        owner = getattr(owner, part)
    last = parts[-1]
    if last not in getattr(owner, "__slots__", ()):
        fields = ", ".join(owner.__slots__)
        raise KeyError(f"{type(owner).__name__} has no field {last!r} (fields: {fields})")
    idx = owner.__slots__.index(last)
    return owner, last, owner.__typenames__[idx]


def set_field(msg: Any, path: str, text: str) -> None:
    """Set the primitive field at dotted *path* from its text form (for ``u2sa pub``).

    ValueError names the field and the expected type when *text* does not parse.
    """
    owner, attr, lcm_type = field_type(msg, path)
    dims = owner.__dimensions__[owner.__slots__.index(attr)]
    try:
        if dims is not None:
            items = [t for t in text.split(",") if t != ""]
            value: Any = [_parse(t, lcm_type) for t in items]
            count_field = dims[0]
            if isinstance(count_field, str) and count_field in owner.__slots__:
                setattr(owner, count_field, len(value))
        else:
            value = _parse(text, lcm_type)
    except ValueError:
        raise ValueError(f"field {path}: expected {lcm_type}, got {text!r}") from None
    if hasattr(owner, "PRESENCE_FIELDS") and attr in owner.PRESENCE_FIELDS:
        owner.set(**{attr: value})
    else:
        setattr(owner, attr, value)


def _parse(text: str, lcm_type: str) -> Any:
    if lcm_type in _INTS:
        return int(text, 0)
    if lcm_type in _FLOATS:
        return float(text)
    if lcm_type == "boolean":
        low = text.lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ValueError(text)
    if lcm_type == "string":
        return text
    raise ValueError(f"cannot set a {lcm_type} from text")
