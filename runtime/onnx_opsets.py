"""The ai.onnx opset of an ONNX file, read from its protobuf without the ``onnx`` package (the cell
has none): ``runtime.bundle`` checks every graph's opset against the manifest and the installed
onnxruntime with it (docs/bundle.md, Verification 4)."""

from __future__ import annotations

from pathlib import Path


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = result = 0
    while True:
        if i >= len(buf):
            raise ValueError("truncated varint")
        b = buf[i]
        i += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, i
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def _fields(buf: bytes):
    """(field number, wire type, value) of one protobuf message; length-delimited values as bytes."""
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wire = key >> 3, key & 7
        if wire == 0:
            val, i = _varint(buf, i)
        elif wire == 1:
            val, i = buf[i:i + 8], i + 8
        elif wire == 2:
            n, i = _varint(buf, i)
            val, i = buf[i:i + n], i + n
            if i > len(buf):
                raise ValueError("truncated field")
        elif wire == 5:
            val, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
        yield num, wire, val


def read_onnx_opsets(path: Path | str) -> dict[str, int]:
    """{domain: version} of an ONNX file's opset_import (ModelProto field 8; "" = ai.onnx)."""
    data = Path(path).read_bytes()
    out: dict[str, int] = {}
    try:
        for num, wire, val in _fields(data):
            if num == 8 and wire == 2:  # OperatorSetIdProto: domain = 1 (string), version = 2 (int64)
                domain, version = "", None
                for n2, w2, v2 in _fields(val):
                    if n2 == 1 and w2 == 2:
                        domain = v2.decode()
                    elif n2 == 2 and w2 == 0:
                        version = v2
                if version is not None:
                    out["" if domain == "ai.onnx" else domain] = int(version)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable ONNX model ({exc})") from exc
    if "" not in out:
        raise ValueError(f"{path}: no ai.onnx opset_import (not an ONNX model?)")
    return out


__all__ = ["read_onnx_opsets"]
