"""Paper 002's network as an identifier: the raw frame in, catalogue ids of the detections out, every answer verified.

1. The network reads head 0's raw frame, preprocessed as in training (:func:`starenv.datasets.preprocess.network_input`:
   the whole frame area-resized to the network's input, background subtracted), and ranks the navigation stars as
   the one nearest the image centre (the paper's "main star"); the ``top_k`` best are tried in turn.  A network
   trained on inputs centred on their main star (config ``centre = "main_star"``) reads the frame once per each of
   the ``centre_stars`` detections nearest the principal point, shifted to put that detection at its centre
   (:func:`starenv.datasets.preprocess.recentred`); each detection's ``top_k`` candidates are tried on it alone,
   the likeliest (detection, candidate) first.
2. A candidate is put on each of the ``centre_stars`` detections nearest the principal point in turn, which fixes
   the attitude but for a turn about that detection's direction.  Each (detection, catalogue star) pair at the same
   angle from the main star's detection and from the main star (within ``radius_px``) votes for the turn that brings
   one onto the other; the ``rolls`` most voted (detection, turn) pairs of the candidate are kept.
3. Each (main star, roll) attitude is verified against the catalogue
   (:func:`starenv.agents.identify.verify.verify_any_search`): detections paired within ``radius_px`` and the
   attitude refined until the pairs settle, then paired and refined again within ``verify_radius_px``; the bound on
   the probability that a wrong attitude pairs that many detections, whatever search found it (the candidates
   tried as sky regions times the two-pair hypotheses of the field, each ``P(X >= m - 2)``,
   ``X ~ Binomial(n - 2, p)``, ``p`` from the catalogue's stars in the field and ``verify_radius_px``), must be at
   most ``max_false`` (default 1e-5, the
   tracking identifier's), with ``min_matches`` pairs.  The first verified hypothesis labels the detections; when
   none verifies, nothing is identified (a wrong main star or a flipped roll never becomes an attitude).

The candidates' directions come from Hipparcos itself, the verification uses the catalogue handed to
:meth:`reset`.  The network only knows the frames it was trained on: head 0 must be the training camera (its
resolution and field of view, from the weights' manifest, checked at :meth:`reset`; another is refused), and the
boresight must lie in the sky region the weights' classes cover.

The frame reaches the identifier through ``images`` (each head's
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

from starenv import checks
from starenv.agents.base import StarMeasurements
from starenv.agents.identify.geometry import body_vectors, with_ids
from starenv.agents.identify.network_model import MAX_PARAMETERS, MainStarConfig, MainStarNet, parameter_count
from starenv.agents.identify.verify import verify_any_search
from starenv.datasets.preprocess import BACKGROUNDS, network_input, recentred
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog, load_catalog

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "paper002_sky_small"  # the whole sky on the bundled paper_002 sensor
CLASS_MAG_LIMIT = 8.0  # the navigation stars' directions come from Hipparcos down to this Hp (classes are brighter)


MAX_MANIFEST_BYTES = 1 << 24  # a manifest holds a config, a class list and per-epoch metrics: far less
MAX_WEIGHTS_BYTES = 4 * MAX_PARAMETERS + (1 << 24)  # float32 parameters, BatchNorm buffers and the zip's own records
IDENTITY_KEYS = ("config", "classes_hip", "camera", "weights_sha256")  # what the identity hash covers


def turned(images: torch.Tensor, quarters: int, about_block: bool) -> torch.Tensor:
    """``images`` (..., S, S) turned by ``quarters`` x 90 deg (``torch.rot90``'s sense): about the image centre, or
    with ``about_block`` about the centre of pixel (S // 2, S // 2), where a network trained on centred inputs reads
    its main star (for an even S one row and column of zeros enter at the edges the turn moves away from).  A
    permutation of pixels (and zeros)."""
    if quarters % 4 == 0:
        return images
    size = images.shape[-1]
    pad = 1 - size % 2 if about_block else 0  # a zero row and column below and right: pixel S // 2 is the centre
    padded = torch.nn.functional.pad(images, (0, pad, 0, pad)) if pad else images
    return torch.rot90(padded, quarters, dims=(-2, -1))[..., :size, :size]


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
        for key in ("width", "height"):
            if not (type(camera.get(key)) is int and camera[key] > 0):
                raise ValueError(f"{path}: camera.{key}: expected a positive number of pixels, got {camera.get(key)!r}")
    return manifest


def shipped_weights(weights: str | Path) -> Path:
    """The run folder ``weights`` names: a folder, or else the name of a shipped run (``paper002_orion``) in
    :data:`WEIGHTS_DIR`, so that scenario and bench files can name shipped weights without a path."""
    path = Path(weights)
    if not path.exists() and path.name == str(weights) and (WEIGHTS_DIR / path.name).is_dir():
        return WEIGHTS_DIR / path.name
    return path


FOV_TOLERANCE = 0.02  # relative: the training field within 2 % (the same optics; a focal length rounded elsewhere)


def check_camera(trained: dict | None, cam: Camera, weights: Path) -> None:
    """Refuse a head 0 that is not the camera the weights were trained on (its manifest's ``camera``: resolution and
    field of view, which with the config's ``input_size`` fix the preprocessing): a ValueError naming both."""
    if trained is None:
        raise ValueError(f"NetworkIdentifier: {weights}: its manifest records no training camera, so head 0 cannot "
                         f"be checked against it; train it again with `starenv train`")
    fov = [math.degrees(a) for a in cam.fov]
    want = trained["fov_deg"]
    if (cam.width, cam.height) != (trained["width"], trained["height"]) or any(
            abs(a - b) > FOV_TOLERANCE * b for a, b in zip(fov, want, strict=True)):
        raise ValueError(f"NetworkIdentifier: the weights {weights.name} were trained for a {trained['width']} x "
                         f"{trained['height']} px, {want[0]:.2f} x {want[1]:.2f} deg camera; head 0 is {cam.width} x "
                         f"{cam.height} px, {fov[0]:.2f} x {fov[1]:.2f} deg (train weights for this sensor: "
                         f"docs/paper002_identification.md)")


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

    ``weights``: a run folder of ``starenv train`` or a shipped run's name (default: the shipped whole-sky
    paper002_sky_small weights; paper002_orion is the 128 px Orion patch); ``top_k``: main-star candidates tried;
    ``rolls``: roll hypotheses per candidate; ``radius_px``: pairing radius of the search (px);
    ``verify_radius_px``: pairing radius of the verification, the bound's (px); ``min_matches``: pairs needed;
    ``max_false``: largest accepted bound on the probability of a wrong attitude per frame;
    ``centre_stars``: detections nearest the principal point each candidate is put on; ``brightest``: those are drawn
    from the ``brightest`` detections by flux only (None: from all; a deep camera's detections nearest the centre are
    mostly stars far fainter than any class);
    ``turns``: 1, 2 or 4 readings of each input, turned by multiples of 90 deg about the point the network reads
    its main star at (:func:`turned`; a turn of the sky keeps the main star, as training's ``--rot90`` uses), their
    log-probabilities averaged; None: 4 for a network trained on centred inputs, 1 for one read whole;
    ``background``: how the frame's background is taken out before the network (``"median"``, as in training, or
    ``"local"`` for a real camera whose background is not flat: :func:`starenv.datasets.preprocess.network_input`);
    ``threads``: torch's CPU thread count, set for the whole process (one frame at a time: one thread is fastest,
    and on a loaded machine threads that wait for busy cores slow a forward pass many times; None leaves torch's
    setting).
    """

    def __init__(self, weights: str | Path = DEFAULT_WEIGHTS, device: str = "cpu", top_k: int = 3, rolls: int = 3,
                 radius_px: float = 2.0, min_matches: int = 5, max_false: float = 1e-5, threads: int | None = 1,
                 centre_stars: int = 5, verify_radius_px: float = 1.0, turns: int | None = None,
                 background: str = "median", brightest: int | None = None):
        if top_k < 1 or rolls < 1 or min_matches < 2 or centre_stars < 1:
            raise ValueError(f"top_k, rolls, centre_stars >= 1 and min_matches >= 2 expected, got {top_k}, {rolls}, "
                             f"{centre_stars}, {min_matches}")
        brightest = None if brightest is None else checks.integer("brightest", brightest, 1, 10**9)
        background = checks.choice("background", background, BACKGROUNDS)
        if turns not in (None, 1, 2, 4):
            raise ValueError(f"turns: expected 1, 2, 4 or None, got {turns!r}")
        if not radius_px > 0 or not verify_radius_px > 0 or not 0 < max_false < 1:
            raise ValueError(f"radius_px, verify_radius_px > 0 and max_false in (0, 1) expected, got {radius_px}, "
                             f"{verify_radius_px}, {max_false}")
        if threads is not None:
            torch.set_num_threads(threads)
        self.weights = shipped_weights(weights)
        self.net, self.manifest = load_network(self.weights, device)
        self.centre_stars = centre_stars
        self.background = background
        self.brightest = brightest
        self.centred = self.net.config.centre == "main_star"
        self.turns = turns if turns is not None else 4 if self.centred else 1
        self.device = device
        self.classes = np.asarray(self.manifest["classes_hip"], dtype=np.int64)
        self.top_k, self.rolls, self.radius_px = top_k, rolls, radius_px
        self.min_matches, self.max_false, self.verify_radius_px = min_matches, max_false, verify_radius_px
        self.catalog: StarCatalog | None = None
        self.last: dict = {}

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        check_camera(self.manifest.get("camera"), cameras[0], self.weights)
        sky = load_catalog(CLASS_MAG_LIMIT, catalog.epoch)
        missing = np.setdiff1d(self.classes, sky.hip)
        if len(missing):
            raise ValueError(f"NetworkIdentifier: {len(missing)} classes (e.g. HIP {missing[0]}) are not Hipparcos "
                             f"stars brighter than Hp {CLASS_MAG_LIMIT}")
        self.class_unit = dict(zip(self.classes.tolist(), sky.unit[np.searchsorted(sky.hip, self.classes)],
                                   strict=True))
        self.catalog = catalog

    @torch.no_grad()
    def rank(self, image: np.ndarray, centres: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Navigation stars (HIP) ranked as the main star of a raw frame, and their softmax probabilities; with
        ``centres`` ((n, 2) px, for a network trained on centred inputs), ranked as the star at each centre: arrays
        (n, classes)."""
        inputs = network_input(image, self.net.config.input_size, background=self.background)
        batch = inputs[None] if centres is None else np.stack([recentred(inputs, image.shape, c) for c in centres])
        batch = torch.from_numpy(batch).to(self.device)
        quarters = range(0, 4, 4 // self.turns)
        readings = torch.cat([turned(batch, q, self.centred) for q in quarters])
        log_prob = torch.log_softmax(self.net(readings), dim=1).reshape(self.turns, len(batch), -1).mean(dim=0)
        prob = torch.softmax(log_prob, dim=1).cpu().numpy()
        order = np.argsort(-prob, axis=1, kind="stable")
        ranked, prob = self.classes[order], np.take_along_axis(prob, order, axis=1)
        return (ranked[0], prob[0]) if centres is None else (ranked, prob)

    def centre_detections(self, stars: StarMeasurements, cam: Camera) -> np.ndarray:
        """Indices of the ``centre_stars`` detections nearest the principal point (among the ``brightest``)."""
        pool = np.arange(len(stars.xy))
        if self.brightest is not None and len(pool) > self.brightest:
            pool = np.sort(np.argsort(-stars.flux, kind="stable")[: self.brightest])
        dist = np.hypot(stars.xy[pool, 0] - cam.cx, stars.xy[pool, 1] - cam.cy)
        return pool[np.argsort(dist, kind="stable")[: self.centre_stars]]

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
        cam, det = cameras[0], stars[0].xy
        centre = self.centre_detections(stars[0], cam)
        t0 = time.perf_counter()
        if self.centred:  # each centre detection's own candidates, the likeliest first
            if not len(centre):
                return none
            ranked, prob = self.rank(images[0], det[centre])
            ranked, prob = ranked[:, : self.top_k].ravel(), prob[:, : self.top_k].ravel()
            order = np.argsort(-prob, kind="stable")
            tries = [(int(ranked[o]), centre[o // self.top_k: o // self.top_k + 1]) for o in order]
            ranked, prob = ranked[order], prob[order]
        else:
            ranked, prob = self.rank(images[0])
            ranked, prob = ranked[: self.top_k], prob[: self.top_k]
            tries = [(int(hip), centre) for hip in ranked]
        self.last["forward_s"] = time.perf_counter() - t0
        self.last["ranked"], self.last["prob"] = ranked, prob
        for hip, attitude in self._hypotheses(cam, det, tries):
            v = verify_any_search(attitude, body, heads, cameras, self.catalog, self.radius_px,
                                  self.verify_radius_px, regions=len(tries))
            if v.matched >= self.min_matches and v.p_false <= self.max_false:
                self.last.update(main=int(hip), verified=True, attitude=v.attitude, p_false=v.p_false,
                                 matched=v.matched)
                return with_ids(stars, v.ids)
        return none

    def _hypotheses(self, cam: Camera, det: np.ndarray,
                    tries: list[tuple[int, np.ndarray]]) -> list[tuple[int, Rotation]]:
        """(main star HIP, inertial -> body attitude) hypotheses of head 0's detections ``det`` (px): for each
        (candidate HIP, detections it is put on) in turn, its ``rolls`` most voted (detection, turn) pairs (see the
        module docstring)."""
        if len(det) < 2:
            return []
        units = cam.unproject(det)  # camera frame
        tol = self.radius_px / max(cam.fx, cam.fy)  # rad
        out = []
        for hip, centre in tries:
            star = self.class_unit[hip]
            rows = self.catalog.cone(star, min(np.pi, 2.0 * cam.half_diagonal))
            ref = self.catalog.unit[rows]
            ref_angle, ref_azimuth, ref_frame = _polar(star, ref)
            votes = []
            for rank, m in enumerate(centre):
                angle, azimuth, frame = _polar(units[m], units)
                i, j = np.nonzero(np.abs(angle[:, None] - ref_angle[None, :]) <= tol)
                keep = (i != m) & (angle[i] > 3 * tol)  # an azimuth next to the main star says little about the turn
                i, j = i[keep], j[keep]
                if not len(i):
                    continue
                turn = np.mod(azimuth[i] - ref_azimuth[j], 2 * np.pi)
                width = tol / np.sin(angle[i])
                diff = np.abs(np.angle(np.exp(1j * (turn[:, None] - turn[None, :]))))
                count = (diff <= width[None, :]).sum(axis=1)
                chosen: list[float] = []
                for k in np.argsort(-count, kind="stable"):
                    if all(abs(np.angle(np.exp(1j * (turn[k] - t)))) > 2 * width[k] for t in chosen):
                        chosen.append(float(turn[k]))
                        votes.append((-int(count[k]), rank, frame, float(turn[k])))
                    if len(chosen) == self.rolls:
                        break
            for _, _, frame, turn in sorted(votes, key=lambda v: v[:2])[: self.rolls]:
                c, s = math.cos(turn), math.sin(turn)
                turned = np.column_stack([frame[:, 0], c * frame[:, 1] + s * frame[:, 2],
                                          -s * frame[:, 1] + c * frame[:, 2]])
                inertial_to_cam = Rotation.from_matrix(turned @ ref_frame.T)
                out.append((int(hip), cam.mounting.inv() * inertial_to_cam))
        return out


def _polar(axis: np.ndarray, units: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles (rad) of ``units`` from ``axis``, their azimuths (rad) about it, and the frame [axis, e1, e2] (columns,
    right-handed) the azimuths are measured in."""
    axis = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, axis)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    cos = np.clip(units @ axis, -1.0, 1.0)
    return np.arccos(cos), np.arctan2(units @ e2, units @ e1), np.column_stack([axis, e1, e2])
