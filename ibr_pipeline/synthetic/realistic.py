"""A phone-camera model: what turns an exact linear render into a photograph (`--realistic`).

Applied per frame, in the order light meets a camera (`degrade`):

1. radial lens distortion (Brown 1966, the k1/k2 model of OpenCV and of COLMAP's RADIAL camera):
   the optical image is warped before it reaches the sensor (`distort_image`);
2. vignetting: radial light fall-off towards the corners (`vignetting`);
3. auto-exposure: a per-frame gain on the light collected (`exposure_gains`);
4. sensor noise in linear units: Poisson shot noise plus Gaussian read noise (`add_sensor_noise`);
5. clipping to the sensor's range [0, 1], the sRGB transfer curve (`srgb_encode`) and 8-bit
   quantisation.

Not modelled: demosaicing (noise is independent per channel), white balance, the phone's own
tone curve, denoising and sharpening, JPEG compression, motion blur, rolling shutter. Every
function is pure numpy (cv2 for the resampling), shape-checked, and deterministic given its rng.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..config import Options, param

# IEC 61966-2-1 sRGB: linear segment below X0 (slope 12.92), power 1/2.4 with offset 0.055 above.
# The standard's decoding threshold 0.04045 is the rounded value of 12.92 * X0 (0.0404499...);
# decoding at exactly 12.92 * X0 makes `srgb_decode` the exact inverse of `srgb_encode`.
_X0 = 0.0031308
_E0 = 12.92 * _X0


@dataclass(frozen=True)
class CaptureModel(Options):
    """The camera of a simulated capture. Defaults: a typical phone main camera indoors, after
    its image processing; each value is a plausible figure for that camera, not a measurement."""

    full_well: float = param(
        2000.0, "shot-noise scale: electrons collected at linear signal 1 (after the ISO gain), so "
                "the shot-noise variance of a signal s is s / full_well; small-pixel phone sensors "
                "at indoor ISO give about 1000-3000 (SNR ~19 at mid-grey 0.18 for 2000)",
        min=1.0)
    read_noise: float = param(
        0.002, "read-noise standard deviation in linear units of full scale (about 4 electrons "
               "at full_well 2000, typical of phone sensors)", min=0.0, max=0.1)
    vignetting: float = param(
        0.25, "light lost in the image corners (0 = none): a lens at a 62 degree field of view "
              "loses ~60 % by the cos^4 law; phones correct most of it and leave about a quarter",
        min=0.0, max=0.9)
    exposure_range: float = param(
        0.3, "auto-exposure: per-frame gain within 1 +- this, varying smoothly along the capture",
        min=0.0, max=0.9)
    k1: float = param(
        0.0, "radial distortion k1 on normalised coordinates (phones after in-camera correction: "
             "|k1| <~ 0.05); 0 because the pipeline does not undistort images",
        min=-0.5, max=0.5)
    k2: float = param(0.0, "radial distortion k2 on normalised coordinates", min=-0.5, max=0.5)

    def noise_scaled(self, scale: float) -> "CaptureModel":
        """The same camera with noise standard deviations multiplied by `scale` (0: no noise)."""
        if not (math.isfinite(scale) and scale >= 0):
            raise ValueError(f"noise scale must be a finite number >= 0, got {scale}")
        return replace(self, full_well=math.inf if scale == 0 else self.full_well / scale ** 2,
                       read_noise=self.read_noise * scale)

    @property
    def distorted(self) -> bool:
        return self.k1 != 0.0 or self.k2 != 0.0


def _image(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)) or a.size == 0:
        raise ValueError(f"{name} must be (H, W) or (H, W, 1|3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return a


# --- tone curve -------------------------------------------------------------------------------
def srgb_encode(linear) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1 opto-electronic transfer); values
    outside [0, 1] are clipped first (the sensor range)."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= _X0, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_decode(encoded) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear [0, 1]: the exact inverse of `srgb_encode`."""
    e = np.clip(np.asarray(encoded, dtype=np.float64), 0.0, 1.0)
    return np.where(e <= _E0, e / 12.92, np.power((e + 0.055) / 1.055, 2.4))


# --- sensor noise -----------------------------------------------------------------------------
def add_sensor_noise(signal, full_well: float, read_noise: float,
                     rng: np.random.Generator) -> np.ndarray:
    """Poissonian-Gaussian raw-sensor noise (Foi et al. 2008, "Practical Poissonian-Gaussian noise
    modeling and fitting for single-image raw-data"): y = Poisson(full_well * s) / full_well +
    N(0, read_noise^2). Mean s, variance s / full_well + read_noise^2. Negative signals count as 0
    photons. Not clipped (the caller clips to the sensor range); full_well = inf: no shot noise."""
    s = _image(signal, "signal")
    if not (full_well > 0 and math.isfinite(read_noise) and read_noise >= 0):
        raise ValueError(f"need full_well > 0 and finite read_noise >= 0, got {full_well}, {read_noise}")
    y = np.maximum(s, 0.0)
    if math.isfinite(full_well):
        y = rng.poisson(y * full_well).astype(np.float64) / full_well
    if read_noise > 0:
        y = y + rng.standard_normal(s.shape) * read_noise
    return y


# --- vignetting -------------------------------------------------------------------------------
def vignetting_factor(rho, corner_attenuation: float) -> np.ndarray:
    """Relative illumination at normalised radius rho (0 = image centre, 1 = a corner).

    The cos^4 law of a pinhole lens (cos^4 theta = (1 + (r/f)^2)^-2, r/f = tan theta), with an
    effective focal length chosen so the corners receive exactly 1 - corner_attenuation:
    v = (1 + c rho^2)^-2, c = (1 - a)^-1/2 - 1. Smooth, monotone, 1 at the centre."""
    if not (0.0 <= corner_attenuation < 1.0):
        raise ValueError(f"corner_attenuation must be in [0, 1), got {corner_attenuation}")
    c = (1.0 - corner_attenuation) ** -0.5 - 1.0
    return (1.0 + c * np.square(np.asarray(rho, dtype=np.float64))) ** -2


def vignetting(width: int, height: int, corner_attenuation: float) -> np.ndarray:
    """(H, W) fall-off map centred on the image centre ((W-1)/2, (H-1)/2), 1 - attenuation at the
    four corner pixels."""
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    cx, cy = (width - 1) / 2, (height - 1) / 2
    r_corner = max(math.hypot(cx, cy), 1e-12)
    u = (np.arange(width) - cx) / r_corner
    v = (np.arange(height) - cy) / r_corner
    return vignetting_factor(np.sqrt(u[None, :] ** 2 + v[:, None] ** 2), corner_attenuation)


# --- auto-exposure ----------------------------------------------------------------------------
def exposure_gains(phase, amplitude: float, rng: np.random.Generator, harmonics: int = 3) -> np.ndarray:
    """Per-frame auto-exposure gains 1 + amplitude * f(phase), phase in [0, 1) along the capture.

    f is a seeded sum of sinusoids of 1..harmonics cycles per capture (amplitudes ~1/k: slow
    drifts dominate, as when a phone's metering follows the brightness of what it looks at),
    scaled so that |f| <= 1 everywhere. Periodic, since the capture is a closed loop; its mean
    over n > harmonics equally spaced frames is 0, so the captures' mean gain is 1. Real
    auto-exposure responds to the scene; this stand-in has the effect that matters to the
    pipeline: frames of the same surfaces differ smoothly in brightness. The same rng state gives
    the same curve whatever phases are asked for."""
    ph = np.asarray(phase, dtype=np.float64)
    if not np.all(np.isfinite(ph)):
        raise ValueError("phase must be finite")
    if not (0.0 <= amplitude < 1.0) or int(harmonics) < 1:
        raise ValueError(f"need 0 <= amplitude < 1 and harmonics >= 1, got {amplitude}, {harmonics}")
    k = np.arange(1, int(harmonics) + 1, dtype=np.float64)
    a = rng.uniform(0.3, 1.0, len(k)) / k
    theta = rng.uniform(0.0, 2 * np.pi, len(k))

    def f(p):
        return np.sum(a * np.sin(2 * np.pi * k * p[..., None] + theta), axis=-1)

    # max |f| from a dense grid plus the most it can rise between grid points (|f'| <= sum 2 pi k a)
    n = 4096
    bound = float(np.abs(f(np.arange(n) / n)).max() + np.sum(2 * np.pi * k * a) / (2 * n))
    return 1.0 + amplitude * f(ph) / bound


# --- lens distortion --------------------------------------------------------------------------
def _intrinsics(K) -> tuple[float, float, float, float]:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0) or K[0, 1] != 0:
        raise ValueError(f"K must be a 3x3 pinhole matrix without skew, got {K.tolist()}")
    return K[0, 0], K[1, 1], K[0, 2], K[1, 2]


def _points(xy) -> np.ndarray:
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim < 1 or p.shape[-1] != 2 or not np.all(np.isfinite(p)):
        raise ValueError(f"points must be finite (..., 2), got shape {p.shape}")
    return p


def distort_points(xy, K, k1: float, k2: float) -> np.ndarray:
    """Pinhole pixels -> distorted pixels: x_d = x_u (1 + k1 r^2 + k2 r^4) on normalised
    coordinates x = (u - c) / f (Brown 1966; OpenCV / COLMAP RADIAL without tangential terms)."""
    fx, fy, cx, cy = _intrinsics(K)
    p = _points(xy)
    x, y = (p[..., 0] - cx) / fx, (p[..., 1] - cy) / fy
    r2 = x * x + y * y
    s = 1 + k1 * r2 + k2 * r2 * r2
    return np.stack([x * s * fx + cx, y * s * fy + cy], axis=-1)


def undistort_points(xy, K, k1: float, k2: float, iterations: int = 50) -> np.ndarray:
    """Distorted pixels -> pinhole pixels, the inverse of `distort_points`: Newton's method on the
    radius, r_u (1 + k1 r_u^2 + k2 r_u^4) = r_d, starting at r_u = r_d (monotone convergence for
    a single-signed k1 with k2 = 0); the direction is unchanged by radial distortion."""
    fx, fy, cx, cy = _intrinsics(K)
    p = _points(xy)
    x, y = (p[..., 0] - cx) / fx, (p[..., 1] - cy) / fy
    rd = np.hypot(x, y)
    r = rd.copy()
    for _ in range(iterations):
        r2 = r * r
        step = (r * (1 + k1 * r2 + k2 * r2 * r2) - rd) / (1 + 3 * k1 * r2 + 5 * k2 * r2 * r2)
        r = np.maximum(r - step, 0.0)
        if np.all(np.abs(step) < 1e-13):
            break
    scale = np.divide(r, rd, out=np.ones_like(rd), where=rd > 0)
    return np.stack([x * scale * fx + cx, y * scale * fy + cy], axis=-1)


def check_distortion(k1: float, k2: float, r_max: float) -> None:
    """ValueError unless r (1 + k1 r^2 + k2 r^4) is increasing up to the radius that reaches
    r_max (a normalised distorted radius): otherwise the image folds over itself."""
    if not (math.isfinite(k1) and math.isfinite(k2) and r_max > 0):
        raise ValueError(f"need finite k1, k2 and r_max > 0, got {k1}, {k2}, {r_max}")
    r = np.linspace(0.0, 4.0 * r_max, 8001)
    f = r * (1 + k1 * r ** 2 + k2 * r ** 4)
    bad = np.nonzero(1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4 <= 0)[0]
    reach = f[bad[0]] if len(bad) else f[-1]
    if reach <= r_max:
        raise ValueError(f"distortion k1={k1}, k2={k2} folds the image over itself before the "
                         f"corner radius {r_max:.3f}")


def corner_radius(K, width: int, height: int) -> float:
    """Largest normalised radius of a pixel centre of a width x height image with intrinsics K."""
    fx, fy, cx, cy = _intrinsics(K)
    xs, ys = np.array([0.0, width - 1.0]), np.array([0.0, height - 1.0])
    return float(np.hypot((xs[:, None] - cx) / fx, (ys[None, :] - cy) / fy).max())


def distortion_padding(K, width: int, height: int, k1: float, k2: float) -> tuple[int, int]:
    """Pixels to add on each side (x, y) of a pinhole render so that it covers every source point
    of the distorted width x height image (barrel distortion pulls them in from outside); two
    spare pixels for the bilinear footprint."""
    check_distortion(k1, k2, corner_radius(K, width, height))
    # radial scaling grows (barrel) or shrinks (pincushion) with the radius, so the farthest
    # source points are those of the frame's border
    u, v = np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)
    zu, zv = np.zeros_like(u), np.zeros_like(v)
    border = np.concatenate([np.stack([u, zu], -1), np.stack([u, zu + height - 1], -1),
                             np.stack([zv, v], -1), np.stack([zv + width - 1, v], -1)])
    src = undistort_points(border, K, k1, k2)
    px = max(0.0, -src[:, 0].min(), src[:, 0].max() - (width - 1))
    py = max(0.0, -src[:, 1].min(), src[:, 1].max() - (height - 1))
    return int(math.ceil(px)) + 2 * (px > 0), int(math.ceil(py)) + 2 * (py > 0)


def distort_image(image, K, k1: float, k2: float, K_out=None,
                  size: tuple[int, int] | None = None) -> np.ndarray:
    """Resample a pinhole image (intrinsics K) into the distorted image of a camera with
    intrinsics K_out (default K) and size (width, height) (default the input's): each output pixel
    takes, by bilinear interpolation (cv2.remap), the colour at undistort_points(pixel) mapped
    into the input. Float32 result; edges replicate (use distortion_padding to avoid needing it)."""
    import cv2

    img = _image(image, "image").astype(np.float32)
    K_out = K if K_out is None else K_out
    w, h = (img.shape[1], img.shape[0]) if size is None else (int(size[0]), int(size[1]))
    check_distortion(k1, k2, corner_radius(K_out, w, h))
    fx, fy, cx, cy = _intrinsics(K)
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    src = undistort_points(np.stack([uu, vv], -1), K_out, k1, k2)
    # undistort_points returns pixels of K_out: re-express them in the input's intrinsics
    ofx, ofy, ocx, ocy = _intrinsics(K_out)
    mx = ((src[..., 0] - ocx) / ofx * fx + cx).astype(np.float32)
    my = ((src[..., 1] - ocy) / ofy * fy + cy).astype(np.float32)
    out = cv2.remap(img, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(h, w, *img.shape[2:])


# --- the whole camera -------------------------------------------------------------------------
def degrade(linear, gain: float, model: CaptureModel, rng: np.random.Generator, K=None,
            K_out=None, size: tuple[int, int] | None = None) -> np.ndarray:
    """A linear render -> the (H, W, 3) uint8 sRGB photograph `model` takes of it at exposure gain
    `gain` (see the module docstring for the order). K / K_out / size: the render's intrinsics,
    the camera's, and its image size, needed only when the model distorts (the render may then
    be larger than the photo: `distortion_padding`). Draws only the noise from rng."""
    img = _image(linear, "linear image")
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"linear image must be (H, W, 3), got {img.shape}")
    if not (math.isfinite(gain) and gain > 0):
        raise ValueError(f"gain must be a finite number > 0, got {gain}")
    if model.distorted:
        if K is None:
            raise ValueError("a distorting capture model needs the render's intrinsics K")
        img = distort_image(img, K, model.k1, model.k2, K_out, size).astype(np.float64)
    elif size is not None and tuple(size) != (img.shape[1], img.shape[0]):
        raise ValueError(f"size {tuple(size)} differs from the image's without distortion")
    h, w = img.shape[:2]
    signal = img * (gain * vignetting(w, h, model.vignetting))[..., None]
    noisy = add_sensor_noise(signal, model.full_well, model.read_noise, rng)
    return np.clip(np.rint(srgb_encode(noisy) * 255.0), 0, 255).astype(np.uint8)
