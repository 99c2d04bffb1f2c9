"""Paper 002's network as an identifier: the raw frame in, catalogue ids of the detections out, every answer verified.

1. The network reads head 0's raw frame and ranks the navigation stars as the one on the boresight (the paper's
   "main star"); the ``top_k`` best are tried in turn.
2. A candidate fixes the boresight direction but not the roll.  The catalogue stars about it are projected at roll
   0; each (detection, catalogue star) pair at the same distance from the principal point (within
   ``radius_px``) votes for the roll that turns one onto the other, and the ``rolls`` most voted rolls are kept.
3. Each (main star, roll) attitude is verified against the catalogue (:mod:`starenv.agents.identify.verify`): detections
   paired within ``radius_px``, the attitude refined, and the false-match probability, times the hypotheses tried,
   compared with ``max_false``; ``min_matches`` pairs are needed.  The first verified hypothesis labels the
   detections; when none verifies, nothing is identified (a wrong main star never becomes an attitude).

The candidates' directions come from Hipparcos itself, the verification uses the catalogue handed to
:meth:`reset`.  The network only knows the frames it was trained on: the camera must have the training field of
view (checked at :meth:`reset`) and the boresight should sit near a navigation star of its classes (the paper's
protocol), in the sky region the weights cover.  The frame reaches the identifier through ``images`` (each head's
frame as the detector saw it, which the pipeline passes); without it nothing is identified.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from starenv.agents.base import StarMeasurements
from starenv.agents.identify.geometry import body_vectors, with_ids
from starenv.agents.identify.network_model import MAX_PARAMETERS, MainStarConfig, MainStarNet, parameter_count
from starenv.agents.identify.verify import verify
from starenv.sim.conventions import pointing, unit_to_radec
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog, load_catalog

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "paper002_orion"
CLASS_MAG_LIMIT = 8.0  # the navigation stars' directions come from Hipparcos down to this Hp (classes are brighter)


MAX_MANIFEST_BYTES = 1 << 24  # a manifest holds a config, a class list and per-epoch metrics: far less
MAX_WEIGHTS_BYTES = 4 * MAX_PARAMETERS + (1 << 24)  # float32 parameters, BatchNorm buffers and the zip's own records
IDENTITY_KEYS = ("config", "classes_hip", "camera", "weights_sha256")  # what the identity hash covers


def manifest_hashes(manifest: dict, weights: bytes) -> dict:
    """The manifest's hashes of a run: ``weights_sha256`` (SHA-256 of weights.pt's bytes) and ``identity_sha256``
    (SHA-256 of the compact sorted JSON of :data:`IDENTITY_KEYS`: config, class order, camera and weights).  They
    catch damaged or inconsistently edited files; whoever can write the folder can recompute them."""
    out = {"weights_sha256": hashlib.sha256(weights).hexdigest()}
    identity = {k: (out if k in out else manifest)[k] for k in IDENTITY_KEYS}
    text = json.dumps(identity, sort_keys=True, separators=(",", ":"))
    out["identity_sha256"] = hashlib.sha256(text.encode()).hexdigest()
    return out


def _checked_manifest(path: Path) -> dict:
    """The manifest at ``path``, its form checked (config, classes, camera, hashes), else ValueError naming it."""
    try:
        if path.stat().st_size > MAX_MANIFEST_BYTES:
            raise ValueError(f"{path}: larger than {MAX_MANIFEST_BYTES} bytes")
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"{path}: not a readable manifest ({type(exc).__name__}: {exc})") from exc
    if not isinstance(manifest, dict):
        raise ValueError(f"{path}: expected a JSON object")
    for key in ("config", "classes_hip", "weights_sha256", "identity_sha256"):
        if key not in manifest:
            raise ValueError(f"{path}: {key}: missing (a manifest of `starenv train`)")
    config = manifest["config"]
    if not isinstance(config, dict):
        raise ValueError(f"{path}: config: expected a table of MainStarConfig fields")
    try:
        config = MainStarConfig.from_dict(config)  # bounded before any tensor exists
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: config: {exc}") from exc
    classes = manifest["classes_hip"]
    if not (isinstance(classes, list) and all(type(h) is int and 0 < h < 2**31 for h in classes)):
        raise ValueError(f"{path}: classes_hip: expected a list of HIP numbers (positive integers)")
    if len(set(classes)) != len(classes) or len(classes) != config.n_classes:
        raise ValueError(f"{path}: classes_hip: expected {config.n_classes} (config.n_classes) distinct HIP numbers, "
                         f"got {len(classes)} with {len(classes) - len(set(classes))} repeated")
    camera = manifest.get("camera")
    if camera is not None:
        fov = camera.get("fov_deg") if isinstance(camera, dict) else None
        if not (isinstance(fov, list) and len(fov) == 2
                and all(isinstance(a, int | float) and not isinstance(a, bool) and 0 < a < 180 for a in fov)):
            raise ValueError(f"{path}: camera.fov_deg: expected two angles in (0, 180) deg, got {fov!r}")
    return manifest


def load_network(folder: str | Path = DEFAULT_WEIGHTS, device: str = "cpu") -> tuple[MainStarNet, dict]:
    """The network of a trained run folder (``weights.pt`` + ``manifest.json``), in eval mode, and its manifest.

    The manifest is checked before anything is allocated: its config bounded (:class:`MainStarConfig`), its class
    list distinct HIP numbers, one per output, its camera's field of view an angle, ``weights.pt``'s SHA-256 and the
    identity hash (:func:`manifest_hashes`) equal to what it records.  Anything else is a ValueError naming the file.
    """
    folder = Path(folder)
    manifest = _checked_manifest(folder / "manifest.json")
    path = folder / "weights.pt"
    try:
        if path.stat().st_size > MAX_WEIGHTS_BYTES:
            raise ValueError(f"{path}: larger than {MAX_WEIGHTS_BYTES} bytes, more than any bounded config needs")
        weights = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot be read ({exc})") from exc
    hashes = manifest_hashes(manifest, weights)
    if hashes["weights_sha256"] != manifest["weights_sha256"]:
        raise ValueError(f"{path}: its SHA-256 is not the manifest's weights_sha256 (damaged or replaced)")
    if hashes["identity_sha256"] != manifest["identity_sha256"]:
        raise ValueError(f"{folder / 'manifest.json'}: its config, classes or camera are not what its identity_sha256 "
                         f"records (edited or damaged)")
    config = MainStarConfig.from_dict(manifest["config"])
    if len(weights) < 4 * parameter_count(config):  # float32: the network is not built for weights that cannot fit
        raise ValueError(f"{path}: {len(weights)} bytes, fewer than the {parameter_count(config)} float32 parameters "
                         f"of its manifest's config")
    net = MainStarNet(config)
    try:
        state = torch.load(io.BytesIO(weights), weights_only=True, map_location=device)
        net.load_state_dict(state)
    except Exception as exc:  # noqa: BLE001  (torch raises many types for a zip or state dict that does not fit)
        raise ValueError(f"{path}: not the weights of its manifest's config ({type(exc).__name__})") from exc
    if not all(torch.isfinite(t).all() for t in state.values() if t.is_floating_point()):
        raise ValueError(f"{path}: holds non-finite values")
    return net.to(device).eval(), manifest


class NetworkIdentifier:
    """Lost-in-space identification by paper 002's network plus catalogue verification (see the module docstring).

    ``weights``: a run folder of ``starenv train`` (default: the shipped paper002_orion weights); ``top_k``: main-star
    candidates tried; ``rolls``: roll hypotheses per candidate; ``radius_px``: pairing radius (px);
    ``min_matches``: pairs needed; ``max_false``: largest accepted false-match probability (all hypotheses);
    ``threads``: torch's CPU thread count, set for the whole process (one frame at a time: one thread is fastest,
    and on a loaded machine threads that wait for busy cores slow a forward pass many times; None leaves torch's
    setting).
    """

    def __init__(self, weights: str | Path = DEFAULT_WEIGHTS, device: str = "cpu", top_k: int = 3, rolls: int = 3,
                 radius_px: float = 2.0, min_matches: int = 5, max_false: float = 1e-3, threads: int | None = 1):
        if top_k < 1 or rolls < 1 or min_matches < 2:
            raise ValueError(f"top_k, rolls >= 1 and min_matches >= 2 expected, got {top_k}, {rolls}, {min_matches}")
        if not radius_px > 0 or not 0 < max_false < 1:
            raise ValueError(f"radius_px > 0 and max_false in (0, 1) expected, got {radius_px}, {max_false}")
        if threads is not None:
            torch.set_num_threads(threads)
        self.net, self.manifest = load_network(weights, device)
        self.device = device
        self.classes = np.asarray(self.manifest["classes_hip"], dtype=np.int64)
        self.top_k, self.rolls, self.radius_px = top_k, rolls, radius_px
        self.min_matches, self.max_false = min_matches, max_false
        self.catalog: StarCatalog | None = None
        self.last: dict = {}

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        fov = math.degrees(cameras[0].fov[0])
        trained = self.manifest.get("camera", {}).get("fov_deg")
        if trained is not None and abs(fov - trained[0]) > 0.02 * trained[0]:
            raise ValueError(f"NetworkIdentifier: head 0's field is {fov:.2f} deg, the network was trained on "
                             f"{trained[0]:.2f} deg")
        sky = load_catalog(CLASS_MAG_LIMIT, catalog.epoch)
        missing = np.setdiff1d(self.classes, sky.hip)
        if len(missing):
            raise ValueError(f"NetworkIdentifier: {len(missing)} classes (e.g. HIP {missing[0]}) are not Hipparcos "
                             f"stars brighter than Hp {CLASS_MAG_LIMIT}")
        self.class_unit = dict(zip(self.classes.tolist(), sky.unit[np.searchsorted(sky.hip, self.classes)],
                                   strict=True))
        self.catalog = catalog

    @torch.no_grad()
    def rank(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Navigation stars (HIP) ranked as the boresight star of a raw frame, and their softmax probabilities."""
        x = torch.from_numpy(np.asarray(image, dtype=np.int32))[None]
        prob = torch.softmax(self.net(x.to(self.device)), dim=1)[0].cpu().numpy()
        order = np.argsort(-prob, kind="stable")
        return self.classes[order], prob[order]

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None = None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """Label all heads' detections (HIP; -1 unidentified) from head 0's frame; ``prior`` is not used."""
        if self.catalog is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        body, heads = body_vectors(stars, cameras)
        none = with_ids(stars, np.full(len(body), -1, dtype=np.int64))
        self.last = {"ranked": None, "main": None, "verified": False}
        if images is None or images[0] is None:
            return none
        t0 = time.perf_counter()
        ranked, prob = self.rank(images[0])
        self.last["forward_s"] = time.perf_counter() - t0
        self.last["ranked"], self.last["prob"] = ranked[: self.top_k], prob[: self.top_k]
        cam = cameras[0]
        det = stars[0].xy
        hypotheses = []
        for hip in ranked[: self.top_k]:
            ra, dec = unit_to_radec(self.class_unit[int(hip)])
            cam0 = pointing(float(ra), float(dec), 0.0)
            for roll in self._rolls(cam, cam0, det):
                hypotheses.append((hip, cam.mounting.inv() * pointing(float(ra), float(dec), roll)))
        trials = max(1, len(hypotheses))
        for hip, attitude in hypotheses:
            v = verify(attitude, body, heads, cameras, self.catalog, self.radius_px, given=1)
            if v.matched >= self.min_matches and v.p_false * trials <= self.max_false:
                self.last.update(main=int(hip), verified=True, attitude=v.attitude, p_false=v.p_false)
                return with_ids(stars, v.ids)
        return none

    def _rolls(self, cam: Camera, cam0: Rotation, det: np.ndarray) -> list[float]:
        """The ``rolls`` most voted rolls (rad) putting catalogue stars about the boresight onto detections."""
        if len(det) == 0:
            return []
        axis = cam0.inv().apply([0.0, 0.0, 1.0])
        rows = self.catalog.cone(axis, cam.half_diagonal)
        xy, front = cam.project(cam0.apply(self.catalog.unit[rows]))
        xy = xy[front]
        c = np.array([cam.cx, cam.cy])
        rc, ac = np.hypot(*(xy - c).T), np.arctan2(*(xy - c).T[::-1])
        rd, ad = np.hypot(*(det - c).T), np.arctan2(*(det - c).T[::-1])
        i, j = np.nonzero(np.abs(rd[:, None] - rc[None, :]) <= self.radius_px)
        keep = rd[i] > 3 * self.radius_px  # the azimuth of a star near the centre says little about the roll
        i, j = i[keep], j[keep]
        if not len(i):
            return []
        roll = np.mod(ac[j] - ad[i], 2 * np.pi)  # pointing(roll) turns the image by -roll
        tol = self.radius_px / rd[i]
        diff = np.abs(np.angle(np.exp(1j * (roll[:, None] - roll[None, :]))))
        votes = (diff <= tol[None, :]).sum(axis=1)
        chosen: list[float] = []
        for k in np.argsort(-votes, kind="stable"):
            if all(abs(np.angle(np.exp(1j * (roll[k] - r)))) > 2 * tol[k] for r in chosen):
                chosen.append(float(roll[k]))
            if len(chosen) == self.rolls:
                break
        return chosen
