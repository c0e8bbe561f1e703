"""Procedural facade textures of the town, BGR uint8 with row 0 at the top of the wall and the bottom row at
street level, the noise and colours they are drawn with, and the sizes of the atlas that holds them."""

from __future__ import annotations

import string

import cv2
import numpy as np

NUM_LEVELS = 5  # mip levels per texture: 1, 1/2, ..., 1/16
_ALIGN_PX = 1 << (NUM_LEVELS - 1)  # texture sizes are multiples of this, so every level halves exactly
PAD_PX = 2  # replicated border around every atlas entry: bilinear taps never bleed into neighbours


def align_px(pixels: float) -> int:
    return max(_ALIGN_PX, int(np.ceil(pixels / _ALIGN_PX)) * _ALIGN_PX)


def smooth_noise(rng: np.random.Generator, height: int, width: int, cell_px: float) -> np.ndarray:
    """Band-limited noise in about [-1, 1]: random values on a coarse grid, bicubically upsampled."""
    rows = max(2, int(height / cell_px) + 2)
    cols = max(2, int(width / cell_px) + 2)
    coarse = rng.uniform(-1.0, 1.0, size=(rows, cols)).astype(np.float32)
    return cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)


def _colour(rng: np.random.Generator, low: int = 0, high: int = 255) -> tuple[int, int, int]:
    value = rng.integers(low, high + 1, size=3)
    return int(value[0]), int(value[1]), int(value[2])


def tinted(rng: np.random.Generator, base: tuple[int, int, int], spread: int) -> tuple[int, int, int]:
    value = np.clip(np.array(base) + rng.integers(-spread, spread + 1, size=3), 0, 255)
    return int(value[0]), int(value[1]), int(value[2])


_LETTERS = list(string.ascii_uppercase + string.digits)
_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)


def _put_text_in_box(
    rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int], colour: tuple[int, int, int]
) -> None:
    """A random word scaled to fill most of the box (x, y, w, h)."""
    x, y, w, h = box
    if w < 8 or h < 6:
        return
    word = "".join(rng.choice(_LETTERS, size=int(rng.integers(3, 9))).tolist())
    font = int(rng.choice(_FONTS))
    thickness = max(1, int(h / 12))
    (text_w, text_h), _ = cv2.getTextSize(word, font, 1.0, thickness)
    scale = min(0.9 * w / max(text_w, 1), 0.75 * h / max(text_h, 1))
    if scale <= 0.05:
        return
    (text_w, text_h), _ = cv2.getTextSize(word, font, scale, thickness)
    cv2.putText(image, word, (x + (w - text_w) // 2, y + (h + text_h) // 2), font, scale, colour, thickness,
                cv2.LINE_AA)


def _draw_shapes(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int], count: int) -> None:
    """Circles, rectangles, triangles and thick strokes: the blobs and corners SIFT feeds on."""
    x, y, w, h = box
    if w < 6 or h < 6:
        return
    for _ in range(count):
        colour = _colour(rng)
        cx, cy = int(x + rng.uniform(0, w)), int(y + rng.uniform(0, h))
        size = max(2, int(rng.uniform(0.08, 0.35) * min(w, h)))
        kind = int(rng.integers(0, 4))
        if kind == 0:
            cv2.circle(image, (cx, cy), size, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(image, (cx - size, cy - size // 2), (cx + size, cy + size // 2), colour, -1)
        elif kind == 2:
            points = np.array([[cx, cy - size], [cx - size, cy + size], [cx + size, cy + size]], dtype=np.int32)
            cv2.fillPoly(image, [points], colour, cv2.LINE_AA)
        else:
            end = (int(cx + rng.uniform(-2, 2) * size), int(cy + rng.uniform(-2, 2) * size))
            cv2.line(image, (cx, cy), end, colour, max(1, size // 4), cv2.LINE_AA)


def _material_shade(rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray, ppm: float) -> np.ndarray:
    """Relative brightness pattern of a wall material: brick, plaster, panels, siding or stone."""
    kind = int(rng.integers(0, 5))
    if kind == 0:  # brick in running bond
        brick_h, brick_w, mortar = 0.075 * ppm, 0.24 * ppm, max(1.0, 0.012 * ppm)
        course = np.floor(rows / brick_h)
        shifted = cols + (course % 2) * brick_w / 2
        brick = np.floor(shifted / brick_w)
        jitter = rng.uniform(-0.18, 0.18, size=(int(course.max()) + 1, int(brick.max()) + 2)).astype(np.float32)
        shade = 1.0 + jitter[course.astype(np.int64), brick.astype(np.int64)]
        return np.where(((rows % brick_h) < mortar) | ((shifted % brick_w) < mortar), 1.35, shade)
    if kind == 1:  # plaster
        return 1.0 + 0.08 * smooth_noise(rng, rows.shape[0], rows.shape[1], 0.6 * ppm)
    if kind == 2:  # concrete panels with seams
        panel_w, panel_h = rng.uniform(0.9, 1.6) * ppm, rng.uniform(0.5, 1.2) * ppm
        seam = max(1.0, 0.02 * ppm)
        panels = rng.uniform(-0.1, 0.1, size=(int(rows.max() / panel_h) + 2, int(cols.max() / panel_w) + 2))
        panel = panels.astype(np.float32)[(rows / panel_h).astype(np.int64), (cols / panel_w).astype(np.int64)]
        return np.where(((rows % panel_h) < seam) | ((cols % panel_w) < seam), 0.6, 1.0 + panel)
    if kind == 3:  # horizontal siding boards
        board = rng.uniform(0.12, 0.22) * ppm
        return 0.85 + 0.25 * (rows % board) / board
    stone_h = rng.uniform(0.25, 0.45) * ppm  # irregular stone courses
    course = np.floor(rows / stone_h).astype(np.int64)
    widths = (rng.uniform(0.3, 0.8, size=int(course.max()) + 1) * ppm).astype(np.float32)
    offsets = (rng.uniform(0, 1, size=int(course.max()) + 1) * ppm).astype(np.float32)
    shifted = cols + offsets[course]
    step = widths[course]
    stone = np.floor(shifted / step).astype(np.int64)
    jitter = rng.uniform(-0.2, 0.2, size=(int(course.max()) + 1, int(stone.max()) + 2)).astype(np.float32)
    joint_px = max(1.0, 0.02 * ppm)
    joint = ((rows % stone_h) < joint_px) | ((shifted % step) < joint_px)
    return np.where(joint, 0.55, 1.0 + jitter[course, stone])


def _material(rng: np.random.Generator, height: int, width: int, ppm: float) -> np.ndarray:
    """Wall material: a colour times a pattern, large stains and fine grain. BGR uint8."""
    base = np.array(_colour(rng, 60, 220), dtype=np.float32)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    shade = _material_shade(rng, rows, cols, ppm)
    stains = 1.0 + 0.12 * smooth_noise(rng, height, width, 1.5 * ppm)
    grain = 1.0 + rng.normal(0.0, 0.03, size=(height, width)).astype(np.float32)
    image = base[None, None, :] * (shade * stains * grain)[:, :, None]
    return np.clip(image, 0, 255).astype(np.uint8)


def _draw_window(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int], ppm: float) -> None:
    """Window with frame, sill and one of: reflection, curtains, blinds, lit room; maybe shutters."""
    x, y, w, h = box
    frame = max(1, int(0.06 * ppm))
    frame_colour = _colour(rng, 150, 255) if rng.random() < 0.6 else _colour(rng, 20, 90)
    cv2.rectangle(image, (x - frame, y - frame), (x + w + frame, y + h + frame), frame_colour, -1)
    cv2.rectangle(image, (x, y), (x + w, y + h), _colour(rng, 15, 70), -1)
    variant = int(rng.integers(0, 5))
    if variant == 0:  # sky reflection band
        shift = int(rng.uniform(0.2, 0.6) * w)
        band = np.array([[x, y + h], [x + shift, y], [x + min(w, shift + w // 3), y], [x + w // 3, y + h]])
        cv2.fillPoly(image, [band.astype(np.int32)], tinted(rng, (150, 140, 130), 40), cv2.LINE_AA)
    elif variant == 1:  # curtains
        colour = _colour(rng, 80, 240)
        curtain = max(2, int(w * rng.uniform(0.2, 0.45)))
        cv2.rectangle(image, (x, y), (x + curtain, y + h), colour, -1)
        cv2.rectangle(image, (x + w - curtain, y), (x + w, y + h), colour, -1)
    elif variant == 2:  # blinds
        slat = max(2, int(0.05 * ppm))
        for row in range(y, y + int(rng.uniform(0.2, 1.0) * h), slat):
            cv2.line(image, (x, row), (x + w, row), tinted(rng, (200, 200, 200), 20), max(1, slat // 2))
    elif variant == 3:  # lit room
        cv2.rectangle(image, (x, y), (x + w, y + h), tinted(rng, (120, 200, 230), 25), -1)
        _draw_shapes(rng, image, (x, y, w, h), 2)
    if rng.random() < 0.7:  # mullions
        cv2.line(image, (x + w // 2, y), (x + w // 2, y + h), frame_colour, frame)
        if rng.random() < 0.5:
            cv2.line(image, (x, y + h // 3), (x + w, y + h // 3), frame_colour, frame)
    sill = max(2, int(0.07 * ppm))
    cv2.rectangle(image, (x - 2 * frame, y + h + frame), (x + w + 2 * frame, y + h + frame + sill),
                  _colour(rng, 150, 240), -1)
    if rng.random() < 0.2:  # shutters
        shutter_colour = _colour(rng, 30, 200)
        for left in (x - frame - w // 2, x + w + frame):
            cv2.rectangle(image, (left, y), (left + w // 2, y + h), shutter_colour, -1)
            for row in range(y, y + h, max(3, int(0.06 * ppm))):
                cv2.line(image, (left, row), (left + w // 2, row), (20, 20, 20), 1)


def _draw_poster(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int]) -> None:
    x, y, w, h = box
    cv2.rectangle(image, (x, y), (x + w, y + h), _colour(rng), -1)
    _draw_shapes(rng, image, box, int(rng.integers(3, 8)))
    _put_text_in_box(rng, image, (x, y + int(0.05 * h), w, int(0.25 * h)), _colour(rng))
    cv2.rectangle(image, (x, y), (x + w, y + h), _colour(rng, 0, 60), 2)


def _draw_shop(rng: np.random.Generator, image: np.ndarray, top: int, door: tuple[int, int], ppm: float) -> None:
    """Sign band with a name above display windows with posters; maybe a striped awning."""
    height, width = image.shape[:2]
    door_x, door_w = door
    sign_h = int(rng.uniform(0.5, 0.9) * ppm)
    sign_y = max(0, top + int(0.2 * ppm))
    cv2.rectangle(image, (0, sign_y), (width, sign_y + sign_h), _colour(rng), -1)
    _put_text_in_box(rng, image, (int(0.05 * width), sign_y, int(0.9 * width), sign_h), _colour(rng))
    pane_top = sign_y + sign_h + int(0.2 * ppm)
    for left, right in ((0, door_x - int(0.2 * ppm)), (door_x + door_w + int(0.2 * ppm), width)):
        if right - left < int(0.8 * ppm):
            continue
        box = (left + int(0.15 * ppm), pane_top, right - left - int(0.3 * ppm), height - pane_top - int(0.5 * ppm))
        cv2.rectangle(image, (box[0], box[1]), (box[0] + box[2], box[1] + box[3]), _colour(rng, 10, 60), -1)
        poster_w, poster_h = int(box[2] * rng.uniform(0.3, 0.6)), int(box[3] * rng.uniform(0.4, 0.8))
        px = box[0] + int(rng.uniform(0, max(1, box[2] - poster_w)))
        py = box[1] + int(rng.uniform(0, max(1, box[3] - poster_h)))
        _draw_poster(rng, image, (px, py, poster_w, poster_h))
    if rng.random() < 0.5:
        stripe = max(2, int(0.25 * ppm))
        colours = (_colour(rng), _colour(rng))
        for index, left in enumerate(range(0, width, stripe)):
            cv2.rectangle(image, (left, sign_y - int(0.1 * ppm)), (left + stripe, sign_y), colours[index % 2], -1)


def _draw_ground_floor(rng: np.random.Generator, image: np.ndarray, top: int, ppm: float) -> None:
    """A door, then a shop front or an entrance with a number plate and small windows."""
    height, width = image.shape[:2]
    door_w, door_h = int(rng.uniform(0.9, 1.4) * ppm), int(rng.uniform(2.1, 2.5) * ppm)
    door_x = int(rng.uniform(0.1, 0.8) * max(1, width - door_w))
    cv2.rectangle(image, (door_x, height - door_h), (door_x + door_w, height), _colour(rng, 20, 160), -1)
    cv2.rectangle(image, (door_x + door_w // 6, height - door_h + door_h // 8),
                  (door_x + door_w - door_w // 6, height - door_h // 2), _colour(rng, 20, 90), -1)
    cv2.circle(image, (door_x + door_w - door_w // 8, height - door_h // 2), max(2, int(0.04 * ppm)),
               (200, 210, 220), -1, cv2.LINE_AA)
    if rng.random() < 0.6:
        _draw_shop(rng, image, top, (door_x, door_w), ppm)
        return
    plate = int(0.3 * ppm)
    px, py = door_x + door_w + int(0.2 * ppm), height - door_h
    cv2.rectangle(image, (px, py), (px + plate, py + plate), (40, 90, 160), -1)
    _put_text_in_box(rng, image, (px, py, plate, plate), (255, 255, 255))
    for _ in range(int(rng.integers(1, 3))):
        w, h = int(0.8 * ppm), int(1.2 * ppm)
        wx = int(rng.uniform(0, max(1, width - w)))
        if abs(wx - door_x) >= door_w + w:
            _draw_window(rng, image, (wx, height - int(2.3 * ppm), w, h), ppm)


def _draw_decals(rng: np.random.Generator, image: np.ndarray, ppm: float) -> None:
    """Pasted posters, graffiti, a drainpipe, air conditioners and small blobs."""
    height, width = image.shape[:2]
    for _ in range(int(rng.integers(0, 3))):
        w, h = int(rng.uniform(0.5, 1.0) * ppm), int(rng.uniform(0.7, 1.3) * ppm)
        x = int(rng.uniform(0, max(1, width - w)))
        y = height - int(rng.uniform(1.0, 2.2) * ppm) - h // 2
        _draw_poster(rng, image, (x, max(0, y), w, h))
    if rng.random() < 0.35:
        colour = _colour(rng)
        for _ in range(int(rng.integers(2, 6))):
            points = np.column_stack([rng.uniform(0, width, 5), height - rng.uniform(0.2, 1.6, 5) * ppm])
            cv2.polylines(image, [points.astype(np.int32)], False, colour, max(2, int(0.05 * ppm)), cv2.LINE_AA)
    if rng.random() < 0.5:
        x = int(rng.choice([int(0.1 * ppm), width - int(0.15 * ppm)]))
        cv2.line(image, (x, 0), (x, height), _colour(rng, 30, 120), max(2, int(0.08 * ppm)))
        for y in range(0, height, max(1, int(1.5 * ppm))):
            cv2.line(image, (x - int(0.06 * ppm), y), (x + int(0.06 * ppm), y), (40, 40, 40), 2)
    for _ in range(int(rng.integers(0, 3))):
        w, h = int(0.8 * ppm), int(0.5 * ppm)
        x, y = int(rng.uniform(0, max(1, width - w))), int(rng.uniform(0, max(1, height - 4 * ppm)))
        cv2.rectangle(image, (x, y), (x + w, y + h), (210, 210, 205), -1)
        cv2.circle(image, (x + w // 3, y + h // 2), max(1, int(0.18 * ppm)), (90, 90, 90), -1, cv2.LINE_AA)
        for gx in range(x + 2 * w // 3, x + w - 2, max(2, int(0.05 * ppm))):
            cv2.line(image, (gx, y + 3), (gx, y + h - 3), (120, 120, 120), 1)
    for _ in range(int(rng.integers(5, 25))):
        centre = (int(rng.uniform(0, width)), int(rng.uniform(0, height)))
        cv2.circle(image, centre, max(2, int(rng.uniform(0.02, 0.15) * ppm)), _colour(rng), -1, cv2.LINE_AA)


def facade_texture(rng: np.random.Generator, width_px: int, height_px: int, ppm: float) -> np.ndarray:
    """A building facade: material, storeys of windows, a ground floor, decals. BGR uint8."""
    image = _material(rng, height_px, width_px, ppm)
    ground_floor_px = int(rng.uniform(3.2, 4.2) * ppm)
    storey_px = int(rng.uniform(2.8, 3.4) * ppm)
    window_w, window_h = int(rng.uniform(0.7, 1.5) * ppm), int(rng.uniform(1.1, 1.7) * ppm)
    count = max(1, int(width_px / (window_w + rng.uniform(0.5, 1.4) * ppm)))
    spacing = width_px / count
    storey_bottom = height_px - ground_floor_px
    while storey_bottom - storey_px >= int(0.5 * ppm):
        window_y = storey_bottom - int(0.9 * ppm) - window_h
        if window_y > 0:
            for index in range(count):
                _draw_window(rng, image, (int((index + 0.5) * spacing - window_w / 2), window_y, window_w, window_h),
                             ppm)
        if rng.random() < 0.3:  # cornice between storeys
            cv2.rectangle(image, (0, storey_bottom - int(0.1 * ppm)), (width_px, storey_bottom),
                          _colour(rng, 100, 230), -1)
        storey_bottom -= storey_px
    _draw_ground_floor(rng, image, height_px - ground_floor_px, ppm)
    _draw_decals(rng, image, ppm)
    return image


def far_texture(rng: np.random.Generator, width_px: int, height_px: int, ppm: float) -> np.ndarray:
    """Distant tall building: material and a regular grid of windows, some lit."""
    image = _material(rng, height_px, width_px, ppm)
    cell_w, cell_h = rng.uniform(1.5, 3.0) * ppm, rng.uniform(2.8, 3.5) * ppm
    dark, lit = _colour(rng, 10, 90), tinted(rng, (140, 210, 235), 20)
    for top in np.arange(0.5 * ppm, height_px - 2 * ppm, cell_h):
        for left in np.arange(0.3 * ppm, width_px - cell_w / 2, cell_w):
            colour = lit if rng.random() < 0.15 else dark
            cv2.rectangle(image, (int(left), int(top)), (int(left + 0.6 * cell_w), int(top + 0.5 * cell_h)),
                          colour, -1)
    return image
