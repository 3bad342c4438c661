"""Texture banks for synthetic scenes: natural images that ship with scikit-image, plus procedural ones.

Train and test scenes draw from *disjoint* banks (different source photographs, different procedural
families and seeds), so a model evaluated on test scenes has never seen their surfaces.

Every texture is a tileable-by-repetition ``(S, S, 3)`` float32 image in [0, 1] whose contrast is
stretched to a common range: photometric learning at 80x60 needs mid-frequency detail everywhere,
and a flat, dark texture would give walls the loss cannot use.
"""

from __future__ import annotations

import functools
import warnings

import cv2
import numpy as np

TEXTURE_SIZE = 256

# skimage.data loaders that work offline (bundled with scikit-image 0.26), split by source photo.
NATURAL_SOURCES = {
    "train": ("astronaut", "brick", "camera", "coffee", "grass", "hubble_deep_field", "moon", "rocket",
              "text", "coins", "cell", "stereo_motorcycle"),
    "test": ("chelsea", "gravel", "immunohistochemistry", "retina", "page", "clock"),
}
PROCEDURAL_FAMILIES = {
    "train": ("fbm", "wood", "bricks", "cells"),
    "test": ("marble", "plaid", "spots", "fbm"),
}
CROPS_PER_PHOTO = 2
VARIANTS_PER_FAMILY = {"train": 4, "test": 3}
_SPLIT_SEEDS = {"train": 1201, "test": 9907}


def _check_split(split: str) -> None:
    if split not in NATURAL_SOURCES:
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")


def _load_photo(name: str) -> np.ndarray:
    import skimage.data

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        image = getattr(skimage.data, name)()
    if isinstance(image, tuple):  # stereo_motorcycle returns (left, right, disparity)
        image = image[0]
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = (255 * (image.astype(np.float64) / max(float(image.max()), 1e-9))).astype(np.uint8)
    return image.astype(np.float32) / 255.0


def _stretch(texture: np.ndarray) -> np.ndarray:
    """Map the 2nd..98th percentile of luminance to [0.08, 0.92], keeping colour ratios."""
    luminance = texture.mean(-1)
    low, high = np.percentile(luminance, [2, 98])
    scale = 0.84 / max(high - low, 1e-3)
    return np.clip((texture - low) * scale + 0.08, 0.0, 1.0).astype(np.float32)


def _colourise(gray: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Duotone: blend between two random colours by intensity, so grayscale photos add colour too."""
    dark, light = rng.uniform(0.0, 0.45, 3), rng.uniform(0.55, 1.0, 3)
    return dark + gray[..., None] * (light - dark)


def _photo_crops(name: str, rng: np.random.Generator, size: int) -> list[np.ndarray]:
    photo = _load_photo(name)
    h, w = photo.shape[:2]
    crops = []
    for _ in range(CROPS_PER_PHOTO):
        side = int(rng.uniform(0.45, 0.8) * min(h, w))
        y, x = rng.integers(0, h - side + 1), rng.integers(0, w - side + 1)
        crop = cv2.resize(photo[y : y + side, x : x + side], (size, size), interpolation=cv2.INTER_AREA)
        if crop.ndim == 2:
            crop = _colourise(crop, rng)
        elif crop.shape[-1] == 4:
            crop = crop[..., :3]
        # Faint multiplicative grain: photos have flat patches (sky, backgrounds) that would give
        # the photometric loss nothing to hold on to.
        crop = crop * (1 + 0.08 * spectral_noise(rng, size, 1.5))
        crops.append(_stretch(crop))
    return crops


def spectral_noise(rng: np.random.Generator, size: int, exponent: float, channels: int = 1) -> np.ndarray:
    """Tileable noise ``(size, size, channels)`` with power spectrum ~ 1/f^exponent, unit std.

    Filtering white noise in the Fourier domain makes it periodic, so it repeats without seams.
    """
    white = rng.standard_normal((channels, size, size))
    frequency = np.sqrt(np.fft.fftfreq(size)[:, None] ** 2 + np.fft.fftfreq(size)[None, :] ** 2)
    frequency[0, 0] = 1.0
    field = np.fft.ifft2(np.fft.fft2(white) / frequency ** (exponent / 2)).real
    field -= field.mean(axis=(1, 2), keepdims=True)
    field /= field.std(axis=(1, 2), keepdims=True)
    return np.moveaxis(field, 0, -1)


def _procedural(family: str, rng: np.random.Generator, size: int) -> np.ndarray:
    grid = np.arange(size) / size
    y, x = np.meshgrid(grid, grid, indexing="ij")
    palette = rng.uniform(0.1, 0.9, (3, 3))
    if family == "fbm":
        noise = spectral_noise(rng, size, rng.uniform(2.0, 3.0), 3)
        texture = 0.5 + 0.18 * noise + 0.1 * noise[..., :1]
    elif family == "wood":
        turbulence = spectral_noise(rng, size, 3.0)[..., 0]
        rings = rng.integers(4, 10)
        grain = np.sin(2 * np.pi * (rings * y + 0.15 * np.sin(2 * np.pi * x) + 0.35 * turbulence))
        fine = spectral_noise(rng, size, 1.2)[..., 0]
        texture = palette[0] + (0.5 + 0.5 * grain[..., None] + 0.1 * fine[..., None]) * (palette[1] - palette[0])
    elif family == "bricks":
        rows = int(rng.integers(4, 9))
        cols = rows // 2
        row = np.floor(y * rows)
        shifted = x * cols + 0.5 * (row % 2)
        column = np.floor(shifted)
        mortar = (np.minimum(y * rows - row, 1 - (y * rows - row)) < 0.06) | (
            np.minimum(shifted - column, 1 - (shifted - column)) < 0.03
        )
        brick_id = (row * 7919 + column * 104729).astype(np.int64) % 997
        tone = np.random.default_rng(int(rng.integers(1 << 31))).uniform(0.6, 1.1, 997)[brick_id]
        noise = spectral_noise(rng, size, 1.5)[..., 0]
        texture = palette[0] * (tone + 0.08 * noise)[..., None]
        texture[mortar] = palette[2] * 0.6 + 0.3
    elif family == "cells":
        seeds = rng.uniform(0, 1, (int(rng.integers(25, 70)), 2))
        # periodic distance, so the Voronoi pattern tiles
        delta = np.abs(np.stack([y, x], -1)[:, :, None, :] - seeds[None, None])
        delta = np.minimum(delta, 1 - delta)
        distance = np.sqrt((delta**2).sum(-1))
        nearest = np.sort(distance, axis=-1)
        cell = np.argmin(distance, -1)
        colours = rng.uniform(0.15, 0.95, (len(seeds), 3))
        edge = np.clip((nearest[..., 1] - nearest[..., 0]) * 40, 0, 1)
        texture = colours[cell] * (0.4 + 0.6 * edge[..., None])
    elif family == "marble":
        turbulence = spectral_noise(rng, size, 3.5)[..., 0]
        phase = 2 * np.pi * (rng.integers(1, 4) * x + rng.integers(1, 4) * y) + 1.5 * turbulence
        veins = (1 - np.abs(np.sin(phase))) ** 3
        cloud = spectral_noise(rng, size, 2.2)[..., 0]
        base = palette[0] * 0.5 + 0.45 + 0.06 * cloud[..., None]
        texture = base - veins[..., None] * (0.7 * base - 0.2 * palette[1])
    elif family == "plaid":
        a, b = rng.integers(3, 9, 2)
        stripes_x = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * a * x))
        stripes_y = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * b * y))
        fine = spectral_noise(rng, size, 1.0)[..., 0]
        texture = (palette[0] * stripes_x[..., None] + palette[1] * stripes_y[..., None]) / 2 + palette[2] * 0.3
        texture = texture + 0.05 * fine[..., None]
    elif family == "spots":
        texture = np.broadcast_to(palette[0], (size, size, 3)).copy()
        for _ in range(int(rng.integers(30, 80))):
            cy, cx, radius = rng.uniform(0, 1), rng.uniform(0, 1), rng.uniform(0.01, 0.08)
            dy = np.minimum(np.abs(y - cy), 1 - np.abs(y - cy))
            dx = np.minimum(np.abs(x - cx), 1 - np.abs(x - cx))
            texture[dy**2 + dx**2 < radius**2] = rng.uniform(0, 1, 3)
    else:
        raise ValueError(f"unknown procedural texture family {family!r}")
    return _stretch(np.clip(texture, 0.0, 1.0))


@functools.lru_cache(maxsize=4)
def texture_bank(split: str, size: int = TEXTURE_SIZE) -> tuple[np.ndarray, tuple[str, ...]]:
    """The texture set of a split: ``(textures (T, size, size, 3) float32 read-only, names)``.

    Deterministic (fixed per-split seeds) and cached per process, so every scene of a split draws
    from the same bank at no extra cost.
    """
    _check_split(split)
    rng = np.random.default_rng(_SPLIT_SEEDS[split])
    textures, names = [], []
    for photo in NATURAL_SOURCES[split]:
        for index, crop in enumerate(_photo_crops(photo, rng, size)):
            textures.append(crop)
            names.append(f"{photo}#{index}")
    for family in PROCEDURAL_FAMILIES[split]:
        for index in range(VARIANTS_PER_FAMILY[split]):
            textures.append(_procedural(family, rng, size))
            names.append(f"{family}#{index}@{split}")
    bank = np.stack(textures).astype(np.float32)
    bank.setflags(write=False)
    return bank, tuple(names)
