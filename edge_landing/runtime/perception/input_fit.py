"""How a camera frame of any size is placed in the model's fixed input, and back (ARCHITECTURE.md §5).

The networks were trained on 240×320 images of a 4:3 camera with square pixels. A 640×480 or 1024×768 frame
is simply shrunk (INTER_AREA). A frame of another shape (1280×720, 1920×1080, 1280×1024) is *letterboxed*:
shrunk by one factor for both axes and mirrored into bands above and below (or left and right) to fill the
input, so pixels stay square and the focal length in input pixels stays what the network learnt (for a 90°
camera, 160 px at 320 wide). Squashing 16:9 into 4:3 instead stretched everything vertically by a third,
which the network reads as other slopes and distances: on the same flights (640×480 renders cropped to
16:9) it halved the candidate landing area and raised the share of unsafe candidates from ~3 % to 12-25 %
(notes in benchmarks/resolution_sweep.py). The outputs are cropped back to the image part, so depth and
HVO maps always cover exactly the camera frame and its intrinsics scale to them with ``Intrinsics.scaled``.

    fit = InputFit.for_frame(720, 1280, 240, 320)    # image 180×320 at rows 30..210 of the 240×320 input
    x = fit.place(rgb)                               # 240×320×3 uint8, bands mirrored
    depth = fit.crop(depth_out)                      # output (any multiple of the input size) -> image part
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Tuple

import cv2
import numpy as np

# A frame whose shape differs from the input's by less than this share is resized as it is: letterboxing a
# 641×480 frame would add a one-pixel band for nothing.
ASPECT_TOLERANCE = 0.01


@dataclass(frozen=True)
class InputFit:
    """Where the camera image sits inside the model input, in input pixels (pixel-edge convention).

    ``top``/``left``: first row/column of the image part; ``height``/``width``: its size. The rest of the
    ``input_hw`` input is mirrored image (a flat band would read as an edge to the network).
    """

    frame_hw: Tuple[int, int]
    input_hw: Tuple[int, int]
    top: int
    left: int
    height: int
    width: int

    @staticmethod
    def for_frame(frame_h: int, frame_w: int, input_h: int, input_w: int) -> InputFit:
        """The placement of a ``frame_h``×``frame_w`` frame in an ``input_h``×``input_w`` input."""
        frame_aspect, input_aspect = frame_w / frame_h, input_w / input_h
        if abs(frame_aspect / input_aspect - 1.0) <= ASPECT_TOLERANCE:
            return InputFit((frame_h, frame_w), (input_h, input_w), 0, 0, input_h, input_w)
        s = min(input_w / frame_w, input_h / frame_h)
        # Even sizes and offsets: the outputs have stride 2, so the image part then ends on an output pixel edge.
        h = min(input_h, max(2, 2 * round(frame_h * s / 2)))
        w = min(input_w, max(2, 2 * round(frame_w * s / 2)))
        top, left = 2 * ((input_h - h) // 4), 2 * ((input_w - w) // 4)
        return InputFit((frame_h, frame_w), (input_h, input_w), top, left, h, w)

    @property
    def letterboxed(self) -> bool:
        return (self.height, self.width) != tuple(self.input_hw)

    def place(self, rgb: np.ndarray) -> np.ndarray:
        """The frame (H×W×C, the size this fit was made for) resized into the model's input size."""
        shrinking = rgb.shape[0] > self.height
        interp = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
        small = rgb if rgb.shape[:2] == (self.height, self.width) else cv2.resize(rgb, (self.width, self.height),
                                                                                  interpolation=interp)
        if not self.letterboxed:
            return small
        ih, iw = self.input_hw
        bottom, right = ih - self.height - self.top, iw - self.width - self.left
        # BORDER_REFLECT_101 needs the band to be narrower than the image; a band wider than that (a frame
        # far from 4:3) falls back to repeating the edge row.
        border = cv2.BORDER_REFLECT_101 if max(self.top, bottom) < self.height and max(self.left, right) < self.width \
            else cv2.BORDER_REPLICATE
        return cv2.copyMakeBorder(small, self.top, bottom, self.left, right, border)

    def crop(self, out: np.ndarray) -> np.ndarray:
        """The image part of a model output map (H'×W' or H'×W'×C at any scale of the input), as a view: a
        copy here would turn a transposed NCHW map into a pixel-interleaved one, on which the softmax over
        3 channels costs ~10× more (0.8 ms at 160×90)."""
        if not self.letterboxed:
            return out
        ih, iw = self.input_hw
        sy, sx = out.shape[0] / ih, out.shape[1] / iw
        r0, r1 = int(round(self.top * sy)), int(round((self.top + self.height) * sy))
        c0, c1 = int(round(self.left * sx)), int(round((self.left + self.width) * sx))
        return out[r0:max(r1, r0 + 1), c0:max(c1, c0 + 1)]


def describe_sizes(frame_hw: Tuple[int, int], input_hw: Tuple[int, int], output_stride: int,
                   fusion_hw: Tuple[int, int]) -> str:
    """One line for edge-run: the size it received, the model's input, the depth/HVO maps of the image part
    (the input's size / ``output_stride``) and fusion's working size. Sizes are written width×height."""
    fit = InputFit.for_frame(frame_hw[0], frame_hw[1], input_hw[0], input_hw[1])
    (fh, fw), (ih, iw), (wh, ww) = frame_hw, input_hw, fusion_hw
    stride = max(1, int(output_stride))
    if fit.letterboxed:
        bands = "above and below" if fit.height < ih else "left and right"
        how = f"letterboxed: image {fit.width}×{fit.height}, mirrored bands {bands}, square pixels kept"
    else:
        how = "shrunk" if fh > ih else ("as is" if (fh, fw) == (ih, iw) else "enlarged")
    oh, ow = fit.crop(np.empty((ih // stride, iw // stride), np.uint8)).shape
    return (f"camera {fw}×{fh} -> model input {iw}×{ih} ({how}); depth/HVO {ow}×{oh}; "
            f"fusion works at {ww}×{wh}")


class _Model(Protocol):
    @property
    def input_hw(self) -> Tuple[int, int]: ...

    @property
    def output_stride(self) -> int: ...


def describe_for_model(model: _Model, frame_hw: Tuple[int, ...], fusion_hw: Tuple[int, int]) -> str:
    """:func:`describe_sizes` for an ``OnnxModel`` (its input size and output stride from its contract)."""
    return describe_sizes((int(frame_hw[0]), int(frame_hw[1])), model.input_hw, model.output_stride, fusion_hw)
