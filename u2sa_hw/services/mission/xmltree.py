"""Line-numbered XML for the mission and world files, and typed readers whose errors point at the source.

``xml.etree`` forgets where an element came from, so the tree is built here from the
``xml.parsers.expat`` events, recording ``parser.CurrentLineNumber`` for every element.
Every error is an :class:`XmlFileError` whose text starts ``FILE:LINE: <element>:``, the
format editors and compilers use, so a user can jump straight to the mistake.
Tag names are matched case-insensitively (the thesis writes ``<Circle>`` and ``<waypoint>``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from xml.parsers import expat


class XmlFileError(ValueError):
    """A mission/world file is not what it must be; the text names the file, line and element."""

    def __init__(self, source: str, line: int | None, element: str | None, problem: str) -> None:
        self.source, self.line, self.element, self.problem = source, line, element, problem
        where = f"{source}:{line}" if line else source
        what = f" <{element}>" if element else ""
        super().__init__(f"{where}:{what} {problem}")


@dataclass
class XmlNode:
    """One element: tag, attributes, its own text (stripped), children and the line it starts on."""

    tag: str
    attrs: dict[str, str]
    line: int
    source: str
    text: str = ""
    children: list["XmlNode"] = field(default_factory=list)

    @property
    def key(self) -> str:
        """The tag in lower case, for matching."""
        return self.tag.lower()

    def error(self, problem: str) -> XmlFileError:
        """An :class:`XmlFileError` located at this element."""
        return XmlFileError(self.source, self.line, self.tag, problem)

    def only_children(self, allowed: dict[str, bool]) -> dict[str, list["XmlNode"]]:
        """Children grouped by lower-case tag; *allowed* maps tag -> may repeat. Unknown or repeated -> error."""
        grouped: dict[str, list[XmlNode]] = {}
        for child in self.children:
            if child.key not in allowed:
                known = ", ".join(f"<{k}>" for k in allowed)
                raise child.error(f"unknown element inside <{self.tag}>; expected one of {known}")
            if grouped.get(child.key) and not allowed[child.key]:
                raise child.error(f"appears twice inside <{self.tag}> (first on line {grouped[child.key][0].line})")
            grouped.setdefault(child.key, []).append(child)
        return grouped

    def number(self) -> float:
        """The element's text as a finite number."""
        try:
            value = float(self.text)
        except ValueError:
            raise self.error(f"expected a number, got {self.text!r}") from None
        if not math.isfinite(value):
            raise self.error(f"expected a finite number, got {self.text!r}")
        return value

    def positive(self) -> float:
        """The element's text as a number > 0."""
        value = self.number()
        if value <= 0:
            raise self.error(f"must be greater than 0, got {self.text!r}")
        return value

    def angle(self) -> float:
        """The element's text as an angle in radians; ``unit="deg"`` marks degrees."""
        unit = self.attrs.get("unit", "rad").strip().lower()
        if unit not in ("rad", "deg"):
            raise self.error(f"unit must be \"rad\" or \"deg\", got {unit!r}")
        value = self.number()
        return math.radians(value) if unit == "deg" else value

    def word(self) -> str:
        """The element's text, which must not be empty."""
        if not self.text:
            raise self.error("must not be empty")
        return self.text


def parse_bool(node: XmlNode, name: str, default: bool) -> bool:
    """The boolean attribute *name* of *node* (true/false, yes/no, 1/0), *default* when absent."""
    raw = node.attrs.get(name)
    if raw is None:
        return default
    low = raw.strip().lower()
    if low in ("true", "yes", "1"):
        return True
    if low in ("false", "no", "0"):
        return False
    raise node.error(f"attribute {name}=\"{raw}\" must be true or false")


def parse_xml(text: str | bytes, *, source: str) -> XmlNode:
    """Parse *text* into an :class:`XmlNode` tree; malformed XML -> :class:`XmlFileError` with its line."""
    parser = expat.ParserCreate()
    stack: list[XmlNode] = []
    roots: list[XmlNode] = []
    texts: list[list[str]] = []

    def start(tag: str, attrs: dict[str, str]) -> None:
        node = XmlNode(tag=tag, attrs=dict(attrs), line=parser.CurrentLineNumber, source=source)
        (stack[-1].children if stack else roots).append(node)
        stack.append(node)
        texts.append([])

    def end(_tag: str) -> None:
        node = stack.pop()
        node.text = "".join(texts.pop()).strip()

    def data(chunk: str) -> None:
        if texts:
            texts[-1].append(chunk)

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = data
    try:
        parser.Parse(text, True)
    except expat.ExpatError as exc:
        element = f"{stack[-1].tag}" if stack else None
        raise XmlFileError(source, exc.lineno, element,
                           f"not well-formed XML: {expat.ErrorString(exc.code)} (column {exc.offset + 1})") from None
    return roots[0]


def read_xml_file(path: Path | str) -> XmlNode:
    """Read and parse the XML file at *path*; a missing or unreadable file -> :class:`XmlFileError`."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise XmlFileError(str(path), None, None, "no such file; check the path in the service's config") from None
    except OSError as exc:
        raise XmlFileError(str(path), None, None, f"cannot read: {exc.strerror or exc}") from None
    return parse_xml(data, source=str(path))
