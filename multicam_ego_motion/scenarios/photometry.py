"""Camera photometric effects for the `lighting` scenario: changing illumination and
exposure, motion blur from turning, and sensor noise."""
import cv2
import numpy as np

EXPOSURE_S = 0.02
NOISE_SIGMA = 3.0      # grey levels, on top of a small signal-dependent part


class LightingEffects:
    def __init__(self, rng: np.random.Generator, fx: float):
        self.rng = rng
        self.fx = fx

    @staticmethod
    def gain(t: float, camera_index: int) -> float:
        """Slow exposure drift per camera, lights dimming to 55 % between 10 s and 12 s and
        coming back between 19 s and 20 s, and a short flicker at 25 s."""
        drift = 1.0 + 0.25 * np.sin(2 * np.pi * t / 11.0 + 1.7 * camera_index)
        dim = 1.0 - 0.45 * (np.clip((t - 10.0) / 2.0, 0, 1) - np.clip((t - 19.0) / 1.0, 0, 1))
        flicker = 1.0 + 0.3 * np.exp(-((t - 25.0) / 0.15) ** 2)
        return float(drift * dim * flicker)

    def apply(self, image: np.ndarray, t: float, camera_index: int, yaw_rate: float) -> np.ndarray:
        # Turning sweeps the image sideways by yaw_rate * fx pixels per second.
        blur_px = int(round(abs(yaw_rate) * self.fx * EXPOSURE_S))
        if blur_px >= 2:
            image = cv2.blur(image, (blur_px, 1), borderType=cv2.BORDER_REPLICATE)
        out = image.astype(np.float32) * np.float32(self.gain(t, camera_index))
        noise = self.rng.standard_normal(out.shape, dtype=np.float32)
        out += noise * (np.float32(NOISE_SIGMA) + np.float32(0.01) * out)
        np.clip(out + np.float32(0.5), 0, 255, out=out)
        return out.astype(np.uint8)
