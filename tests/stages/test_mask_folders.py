"""Mask folders (an object's mask_dir): another aspect ratio and decompression bombs are refused, naming the file (issue 38)."""

from __future__ import annotations

import pytest


def test_mask_of_another_aspect_refused(tmp_path):
    import cv2
    import numpy as np

    from cobgs.data.images import same_aspect
    from cobgs.masks.sources import folder_masks as _folder_masks

    class V:
        def __init__(self, name, w, h):
            self.name, self.width, self.height = name, w, h

    folder = tmp_path / "m"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.full((160, 120), 255, np.uint8))  # 120x160: transposed
    cv2.imwrite(str(folder / "b.png"), np.full((240, 320), 255, np.uint8))  # 320x240: 2x, same aspect
    from cobgs.errors import InputError

    with pytest.raises(InputError, match=r"a\.png: 120x160 px, but view 'a' is 160x120: another aspect"):
        _folder_masks([V("a", 160, 120)], folder, 0)
    out, info = _folder_masks([V("b", 160, 120)], folder, 0)
    assert out["b"].shape == (120, 160) and info["resized_nearest"] == ["b"]
    assert same_aspect(4032, 3024, 1008, 756) and same_aspect(510, 382, 512, 384)
    assert not same_aspect(120, 160, 160, 120)

def test_huge_mask_png_named(tmp_path):
    import zlib

    from cobgs.errors import DataError
    from cobgs.masks.sources import folder_masks as _folder_masks

    class V:
        name, width, height = "a", 20000, 20000

    # a valid 20000x20000 1-bit PNG written by hand (tiny on disk, 400 Mpx decoded)
    def chunk(tag, data):
        import struct

        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    import struct

    raw = zlib.compress(b"".join(b"\x00" + b"\x00" * 2500 for _ in range(20000)), 9)
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 20000, 20000, 1, 0, 0, 0, 0))
           + chunk(b"IDAT", raw) + chunk(b"IEND", b""))
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "a.png").write_bytes(png)
    with pytest.raises(DataError, match=r"a\.png: cannot read it as an image .*decompression bomb"):
        _folder_masks([V()], folder, 0)
