"""PLY headers: the element counts a header declares, checked against the file's size before
any reader allocates for them (a 1 kB file declaring 2 × 10⁹ vertices would otherwise end in
``bad_alloc`` or the OOM killer). Used by the object upload and by the worker that loads the
model."""

from __future__ import annotations

# Bytes of one PLY scalar (binary) by type name.
PLY_SCALAR_BYTES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1,
    "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
    "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
    "double": 8, "float64": 8,
}  # fmt: skip


def ply_count_problem(head: bytes, size_bytes: int) -> str | None:
    """Why the header at the start of ``head`` promises more than a file of ``size_bytes``
    holds, or None. Each element needs at least its binary size (a list at least its count)
    or, in ASCII, two characters per value. A header without ``end_header``, an element
    without a whole-number count and an unknown property type are problems too."""
    end = head.find(b"end_header")
    if end < 0:
        return "the PLY header has no 'end_header' line"
    newline = head.find(b"\n", end)
    body = size_bytes - (newline + 1 if newline >= 0 else len(head))
    binary = False
    elements: list[list[str | int]] = []  # [name, count, bytes at least]
    for line in head[:end].decode("latin-1").splitlines():
        words = line.split()
        if len(words) >= 2 and words[0] == "format":
            binary = words[1].startswith("binary")
        elif len(words) == 3 and words[0] == "element":
            if not (words[2].isascii() and words[2].isdigit()):
                return f"element {words[1]!r} has no count"
            elements.append([words[1], int(words[2]), 0])
        elif len(words) >= 3 and words[0] == "property" and elements:
            kind = words[2] if words[1] == "list" else words[1]
            if kind not in PLY_SCALAR_BYTES:
                return f"unknown PLY property type {kind!r}"
            elements[-1][2] = int(elements[-1][2]) + (PLY_SCALAR_BYTES[kind] if binary else 2)
    for name, count, at_least in elements:
        need = int(count) * int(at_least)
        if need > body:
            return (
                f"the header declares {count} {name} elements, which need at least "
                f"{need} bytes, but the file holds {body} after its header"
            )
    return None
