#!/usr/bin/env python3
"""Writes the seed inputs of the fuzz harness (fuzz/, scripts/fuzz.sh) into CORPUS_DIR/<target>/.

Small valid files of every format each reader takes, made here (nothing large is committed):
OpenEXR (uncompressed, float RGB), Radiance HDR (flat RGBE), PNG (RGB8), the shipped configs,
a poses.csv and the shipped model's state.toml. The image seeds start with the byte that picks
their format in the image target.
"""
import pathlib
import struct
import sys
import zlib

root = pathlib.Path(__file__).resolve().parent.parent
out = pathlib.Path(sys.argv[1])
W, H = 16, 8


def texel(x, y):
    return (0.1 + x / W, 0.2 + y / H, 0.5)


def exr():
    def attr(name, kind, value):
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    channels = b"".join(c + b"\0" + struct.pack("<iBBBBii", 2, 0, 0, 0, 0, 1, 1) for c in (b"B", b"G", b"R")) + b"\0"
    box = struct.pack("<iiii", 0, 0, W - 1, H - 1)
    header = (
        attr("channels", "chlist", channels)
        + attr("compression", "compression", b"\0")
        + attr("dataWindow", "box2i", box)
        + attr("displayWindow", "box2i", box)
        + attr("lineOrder", "lineOrder", b"\0")
        + attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
        + attr("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0))
        + attr("screenWindowWidth", "float", struct.pack("<f", 1.0))
        + b"\0"
    )
    start = 8 + len(header) + 8 * H
    line_bytes = 4 + 4 + 3 * 4 * W
    offsets = b"".join(struct.pack("<Q", start + y * line_bytes) for y in range(H))
    lines = b""
    for y in range(H):
        px = [texel(x, y) for x in range(W)]
        data = b"".join(struct.pack("<f", p[c]) for c in (2, 1, 0) for p in px)
        lines += struct.pack("<ii", y, len(data)) + data
    return struct.pack("<ii", 20000630, 2) + header + offsets + lines


def rgbe(c):
    import math
    m = max(c)
    if m < 1e-32:
        return bytes(4)
    e = math.frexp(m)[1]
    s = 256.0 / 2.0 ** e
    return bytes([int(v * s) for v in c] + [e + 128])


def hdr():
    head = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {H} +X {W}\n".encode()
    return head + b"".join(rgbe(texel(x, y)) for y in range(H) for x in range(W))


def png():
    raw = b"".join(b"\0" + bytes(min(255, int(255 * v)) for x in range(W) for v in texel(x, y)) for y in range(H))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", W, H, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def write(target, name, data):
    d = out / target
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_bytes(data)


write("image_readers", "map.exr", b"\0" + exr())
write("image_readers", "map.hdr", b"\1" + hdr())
write("image_readers", "map.png", b"\2" + png())
for config in sorted((root / "configs").glob("*.toml")):
    write("train_config", config.name, config.read_bytes())
write("poses_csv", "poses.csv", b"name,yaw,pitch\na,0.1,0.0\nb,-0.3,0.05\nc,0.0,-0.1\n")
write("checkpoint_state", "state.toml", (root / "assets/models/quickstart/state.toml").read_bytes())
