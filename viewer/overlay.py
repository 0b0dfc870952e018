"""The viewer's text overlay, drawn into the 8-bit frame on the CPU (Pillow's built-in font): it
shows in screenshots and needs no GL state of its own beside the renderer's."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from PIL import Image, ImageDraw

LINE_PX = 13


def draw_overlay(image8: NDArray[np.uint8], lines: Sequence[str]) -> NDArray[np.uint8]:
    """``image8`` with ``lines`` of text over a dark band at its top."""
    img = Image.fromarray(np.ascontiguousarray(image8), "RGB")
    draw = ImageDraw.Draw(img, "RGBA")
    band = 6 + LINE_PX * len(lines)
    draw.rectangle((0, 0, img.width, band), fill=(0, 0, 0, 150))
    for i, line in enumerate(lines):
        draw.text((6, 3 + LINE_PX * i), line, fill=(235, 235, 235))
    return np.asarray(img)


def status_frame(line: str, width: int, height: int, background: NDArray[np.uint8] | None) -> NDArray[np.uint8]:
    """A frame saying ``line`` (a progress step): the last image dimmed, or dark grey."""
    if background is not None and background.shape[:2] == (height, width):
        base = (background.astype(np.float32) * 0.35).astype(np.uint8)
    else:
        base = np.full((height, width, 3), 24, np.uint8)
    words, rows, cur = line.split(), [], ""
    per_row = max(20, width // 7)
    for w in words:                         # wrap: long progress lines fit the window
        if len(cur) + len(w) + 1 > per_row and cur:
            rows.append(cur)
            cur = w
        else:
            cur = f"{cur} {w}".strip()
    rows.append(cur)
    return draw_overlay(base, ["working ..."] + rows)
