"""XML files in any encoding OpenSim reads, decoded without losing their structure.

An XML file names its encoding in a byte-order mark or in its declaration
(``<?xml version="1.0" encoding="windows-1252"?>``); without either it is
UTF-8. OpenSim's own reader accepts files whose declaration says UTF-8 (or
nothing) while a comment or a citation holds a Windows-1252 or Latin-1 byte
(an author's name, a typographic quote), so skelid reads them too:

1. a byte-order mark (UTF-8, UTF-16, UTF-32) decides;
2. otherwise a declared encoding other than UTF-8 decides (an unknown one is
   refused in one line);
3. otherwise the bytes are UTF-8, and a byte that is not part of a valid UTF-8
   sequence is read as Windows-1252 (Latin-1 for the five bytes Windows-1252
   leaves undefined).

Every byte of XML markup (``<``, ``>``, ``=``, quotes, names of elements and
attributes in OpenSim files) is ASCII, which is valid UTF-8 and the same in
every encoding above, so step 3 changes only the characters of text and
comments: it cannot move, merge or drop an element.
"""

from __future__ import annotations

import codecs
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from skelid.errors import FormatError, ModelError
from skelid.io._common import as_path

_BOMS = ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"), (codecs.BOM_UTF8, "utf-8-sig"),
         (codecs.BOM_UTF16_LE, "utf-16"), (codecs.BOM_UTF16_BE, "utf-16"))
_DECLARATION = re.compile(rb"""^\s*<\?xml[^>]*?\bencoding\s*=\s*["']([A-Za-z][A-Za-z0-9._-]*)["']""")
_FALLBACK = "skelid.cp1252-bytes"


def _single_bytes(exc: UnicodeDecodeError) -> tuple[str, int]:
    """Decode the bytes a codec refused one by one as Windows-1252 (Latin-1 where it has no character)."""
    out = []
    for b in exc.object[exc.start:exc.end]:
        try:
            out.append(bytes([b]).decode("cp1252"))
        except UnicodeDecodeError:
            out.append(chr(b))
    return "".join(out), exc.end


codecs.register_error(_FALLBACK, _single_bytes)


def encoding_of(data: bytes) -> str:
    """The codec an XML document's bytes name: byte-order mark, then declaration, else ``utf-8``."""
    for bom, codec in _BOMS:
        if data.startswith(bom):
            return codec
    m = _DECLARATION.match(data[:1024])
    return m.group(1).decode("ascii").lower() if m else "utf-8"


def decode_xml(data: bytes, source: str = "XML file") -> str:
    """The text of an XML document (see the module docstring for the rules).

    Parameters
    ----------
    data : bytes
        The file's content.
    source : str
        Named in the error.

    Returns
    -------
    str

    Raises
    ------
    FormatError
        If the declared encoding is unknown.
    """
    codec = encoding_of(data)
    try:
        info = codecs.lookup(codec)
    except LookupError:
        raise FormatError(f"{source}: unknown encoding {codec!r} in the XML declaration",
                          "save the file as UTF-8 (or declare an encoding such as windows-1252)") from None
    if info.name in ("utf-16", "utf-32"):  # a byte-order mark was found: no byte-by-byte fallback here
        try:
            return data.decode(codec)
        except UnicodeDecodeError as exc:
            raise FormatError(f"{source}: not valid {info.name} text ({exc.reason} at byte {exc.start})",
                              "save the file again as UTF-8") from None
    return data.decode(codec, errors=_FALLBACK)


def read_xml(path, what: str = "file") -> ET.ElementTree:
    """Parse the XML file ``path`` in whatever encoding it is written (:func:`decode_xml`).

    Raises
    ------
    ModelError
        If the file does not exist or cannot be read.
    FormatError
        If it is not well-formed XML, or its encoding is unknown.
    """
    path = as_path(path, what, ModelError)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ModelError(f"{what} {path} does not exist", "check the path") from None
    except OSError as exc:
        raise ModelError(f"cannot read {path}: {exc.strerror or exc}", "check the path and permissions") from None
    text = decode_xml(data, str(path))
    try:
        return ET.ElementTree(ET.fromstring(text))
    except ET.ParseError as exc:
        raise FormatError(f"{path}: malformed XML ({exc})", "repair the file or export it again from OpenSim") \
            from None


def first_tag(path, skip: str = "OpenSimDocument") -> str | None:
    """The tag of the first element that is not ``skip`` (None when the file cannot be read as XML)."""
    try:
        text = decode_xml(Path(path).read_bytes(), str(path))
    except (OSError, FormatError):
        return None
    parser = ET.XMLPullParser(events=("start",))
    try:
        for k in range(0, len(text), 65536):
            parser.feed(text[k:k + 65536])
            for _, el in parser.read_events():
                if el.tag != skip:
                    return el.tag
    except ET.ParseError:
        return None
    return None
