"""Unknown keys in a profile or config table: one line each, with a did-you-mean.

Every table of the vehicle profile (``[vehicle]``, ``[services.X]``, its ``settings`` and
``supervision``, ``[simulation]``, ``[devices.X]``) is checked with :func:`unknown_key_problems`,
so a typo (``log_levle``, ``prot``) is an error that names the file, the key and the fix
instead of a value silently left at its default.

A service setting of the old profile form, which spread a device's address over driver
settings (``port`` + ``baudrate``, ``bus`` + ``address``, ``interface`` + ``channel`` +
``bitrate``, ``chip``), is no setting of any driver any more: :func:`old_form_problem` gives
the one line that names the key and the new form (a ``[devices.NAME]`` address the service
names), for ``u2sa check`` and for a service's start alike.

    >>> did_you_mean("prot", ["port", "baudrate"])
    "did you mean 'port'?"
    >>> unknown_key_problems({"prot": 1}, ["port", "baudrate"], where="vehicle.toml [services.gps] settings")
    ["vehicle.toml [services.gps] settings: unknown key 'prot'; did you mean 'port'? (known: baudrate, port)"]
"""

from __future__ import annotations

from typing import Iterable, Mapping

# difflib's own default: a swapped pair in a short word still matches ("prot" -> "port" scores 0.75),
# and below it suggestions turn into noise.
_CUTOFF = 0.6
_MAX_LISTED = 30   # a table with more known keys lists the closest few instead of all


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"did you mean 'X'?"`` for the choice closest to *word* (a case-insensitive match first), else ""."""
    options = [str(c) for c in choices]
    for option in options:
        if option.lower() == word.lower() and option != word:
            return f"did you mean '{option}'?"
    import difflib   # only when a key is misspelt
    close = difflib.get_close_matches(word, options, n=1, cutoff=_CUTOFF)
    return f"did you mean '{close[0]}'?" if close else ""


def known_text(choices: Iterable[str]) -> str:
    """The known keys, sorted and comma separated (``none`` when there are none)."""
    names = sorted(str(c) for c in choices)
    if len(names) > _MAX_LISTED:
        names = names[:_MAX_LISTED] + [f"... ({len(names) - _MAX_LISTED} more)"]
    return ", ".join(names) or "none"


def unknown_key_problem(key: str, known: Iterable[str], *, where: str, what: str = "key") -> str:
    """One line: *where*, the unknown *key* (a *what*: "key", "service kind"...), a did-you-mean, the known ones."""
    options = list(known)
    hint = did_you_mean(key, options)
    return f"{where}: unknown {what} '{key}'" + (f"; {hint}" if hint else "") + f" (known: {known_text(options)})"


def unknown_key_problems(table: Mapping[str, object], known: Iterable[str], *, where: str,
                         what: str = "key") -> list[str]:
    """One line per key of *table* not in *known* (see :func:`unknown_key_problem`); [] when all are known."""
    options = list(known)
    allowed = set(options)
    return [unknown_key_problem(str(k), options, where=where, what=what) for k in table if k not in allowed]


# The old profile form's address settings (retired in 0.1, which has no users to migrate) -> an address of the new
# form that replaces them (docs/ports.md "Addresses"). A kind that has a field of one of these names (an IMU's
# ``chip`` variant) never meets this: only a key that is not a field is looked up here.
_SERIAL = "serial:///dev/ttyUSB0?baud=9600"
_I2C = "i2c://1/0x68"
_CAN = "can://socketcan/can0?bitrate=500000"
OLD_FORM_KEYS: dict[str, str] = {
    "port": _SERIAL, "baudrate": _SERIAL, "bytesize": _SERIAL, "parity": _SERIAL, "stopbits": _SERIAL,
    "bus": _I2C, "address": _I2C,
    "interface": _CAN, "channel": _CAN, "bitrate": _CAN, "udp_port": _CAN,
    "chip": "gpio://gpiochip0/5,6,13,21",
}
OLD_FORM_DOC = "docs/ports.md"


def old_form_keys(values: Mapping[str, object], fields: Iterable[str]) -> list[str]:
    """The keys of *values* (a service's settings or config file) that are old-form address settings: not one
    of *fields* (the kind's), in :data:`OLD_FORM_KEYS`, and the kind a driver (it has a ``device`` setting)."""
    known = set(fields)
    return [str(k) for k in values if "device" in known and k not in known and k in OLD_FORM_KEYS]


def old_form_fix(key: str, *, device: str = "NAME", example: str | None = None, name_it: str = "") -> str | None:
    """What replaces *key*, a setting of the old profile form (see :data:`OLD_FORM_KEYS`), else None.

    *device* is the device the service would name (its ``device`` setting, else its name);
    *example* an address other than the key's usual one; *name_it* where ``device = "..."`` goes
    when not in the service's settings (a PWM channel's table).
    """
    address = example or OLD_FORM_KEYS.get(key)
    if address is None:
        return None
    where_named = f" {name_it}" if name_it else ""
    return (f"name a device instead: [devices.{device}] address = \"{address}\" and device = \"{device}\""
            f"{where_named} ({OLD_FORM_DOC})")


def old_form_problem(key: str, *, where: str, device: str = "NAME", example: str | None = None,
                     name_it: str = "") -> str | None:
    """One line naming *where* (the table), the old-form *key* and the new form (:func:`old_form_fix`), else None.

    >>> print(old_form_problem("port", where="services.gps", device="gps"))
    services.gps: 'port' is the old form: name a device instead: [devices.gps] address = "serial:///dev/ttyUSB0?baud=9600" and device = "gps" (docs/ports.md)
    """
    fix = old_form_fix(key, device=device, example=example, name_it=name_it)
    return None if fix is None else f"{where}: '{key}' is the old form: {fix}"


# The old form's keys of a [devices.NAME] table (retired with the settings above) -> what replaces them.
OLD_DEVICE_KEYS: dict[str, str] = {
    "usb": "the address's usb and serial parameters, e.g. address = "
           "\"serial:///dev/u2sa/gps?baud=9600&usb=1546:01a7&serial=0123456\"",
    "can": "the address's bitrate parameter, e.g. address = \"can://socketcan/can0?bitrate=500000\"",
}


def old_device_key_fix(key: str) -> str | None:
    """What replaces *key* of a ``[devices.NAME]`` table of the old form (``usb``, ``can``), else None."""
    fix = OLD_DEVICE_KEYS.get(key)
    return None if fix is None else f"write it into {fix} ({OLD_FORM_DOC})"
