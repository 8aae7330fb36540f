"""Stage ``matte``: an alpha matte for every captured image (MODNet-style network).

Steps:
1. The matting network is trained once per training config, on virtual-studio renders of
   OTHER subjects (``stages.matte.studio_data``: other identity seeds, other performances,
   F and OLAT lighting, exact alpha; augmented with exposure, noise and blur), and kept in
   the workspace root's shared cache (``stages.matte.model_cache``, keyed by a hash of the
   training params, the image scale and the code), so every subject reuses it.
2. SOC adaptation (MODNet's sub-objectives consistency) on unlabelled frames of this capture.
3. Inference over every image (fused matte gated by the semantic branch,
   ``stages.matte.inference``), written as 16-bit PNG mattes. Each image is one item fanned
   out through ``ctx.executor`` (``gpu=True`` on CUDA) and cached per image in the stage's
   ``cache_dir``, keyed by the adapted model's weights digest, the image's and its guide's
   bytes and the inference settings: a rerun mattes only the images whose key is new.

Adding frames to a capture: the supervised model does not depend on this capture (other
subjects), but two things do: SOC adaptation samples frames of this capture, and each
camera's exposure reference is the median over its F frames. With ``statistics_frames``
unset both see every frame, so new frames change the adapted weights (and the references)
and every image is matted again. With ``statistics_frames: N`` both use only the first N
frames, so frames appended later leave the model and the references unchanged and only the
new images are matted.

OLAT frames: the unlit side of the head is black, so the image alone cannot say where the
head ends there. Every image goes to the network together with the nearest full-on (F)
frame of the same camera as 3 extra input channels (an F frame is its own guide). The F
frame is at most one frame-time (1/24 s) away in the OLAT pattern F, O, O, F, so the head
has moved by a pixel or two: the network takes the silhouette from the guide and the exact
edge from the OLAT image wherever the edge is lit. It is trained on exactly such pairs
(the studio renders frame t under one bar and frame t +- 1 under all bars).

``method: baseline`` replaces the network by the classical threshold + guided-filter matte
(``stages.matte.baseline``), the fallback when no model can be trained.

Output::

    mattes/<cam>/<index:06d>.png   16-bit alpha, one per received image
    contact_sheet.png              mattes of a few frames from every camera (F and OLAT)
    model.json                     which model was used (key, adapted weights' digest), its training
                                   and SOC loss records; no timings, so a rerun writes the same bytes
    metrics.json                   images_per_second (EXR read + network, images matted by this run;
                                   from the cached per-image times when every image was reused),
                                   training_seconds and training_render_seconds (0 when the model
                                   came from the cache),
                                   model_cached, soc_seconds, images, inference_seconds,
                                   images_reused, images_computed (per-image cache)
"""

from __future__ import annotations

import time
from collections import OrderedDict
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from pipeline.devices import DeviceChoice, resolve_device
from pipeline.stage import Stage, StageContext, StageParams
from scene.rig import RigConfig, default_rig
from stages.capture.output import CaptureOutput
from stages.matte.baseline import BaselineConfig
from stages.matte.contact_sheet import write_contact_sheet
from stages.matte.inputs import (bright_level, camera_reference, is_full_on, nearest_full_on, network_input,
                                 olat_scale)
from stages.matte.model_cache import cache_key, load_or_train, training_code_digest
from stages.matte.output import MatteOutput
from stages.matte.studio_data import StudioDataConfig, collect, identity_jobs, render_identity
from stages.matte.training import InputConfig, SocConfig, TrainConfig, soc_adapt, train_supervised



class MatteParams(StageParams):
    """Params of the matte stage."""

    method: Literal["modnet", "baseline"] = Field("modnet", description="'modnet' (the network) or 'baseline' (threshold + guided filter).")
    train: TrainConfig = Field(TrainConfig(), description="Supervised training of the network (cached across subjects).")
    data: StudioDataConfig = Field(StudioDataConfig(), description="Studio renders of other subjects used for training.")
    soc: SocConfig = Field(SocConfig(), description="SOC adaptation on unlabelled frames of this capture.")
    soc_frames: int = Field(32, ge=0, description="Unlabelled frames (spread over cameras and lights) used by SOC.")
    baseline: BaselineConfig = Field(BaselineConfig(), description="The classical matte (method 'baseline').")
    gate_low: float = Field(0.3, ge=0, lt=1, description="Semantic gate: matte forced to 0 where the dilated semantic foreground is below this (0 = no gate).")
    gate_high: float = Field(0.6, gt=0, le=1, description="Semantic gate: matte kept as is where the dilated semantic foreground is above this.")
    device: DeviceChoice = Field("auto", description="Torch device; 'auto' uses CUDA when present.")
    contact_sheet_frames: int = Field(4, ge=1, description="Frames (rows) shown in the contact sheet.")
    rig: RigConfig = Field(default_factory=default_rig,
                           description="The studio rig (injected from configs/rig.yaml, or the subject's rig file): "
                           "the training data is filmed with its cameras, so the training heads are framed as the "
                           "capture frames the subject.")
    statistics_frames: int | None = Field(
        None, ge=1, description="Only frames with index below this set the cameras' exposure references and "
        "feed SOC adaptation (None = every frame). Set it so that frames appended to a capture later leave the "
        "adapted model unchanged and only the new images are matted again (per-image cache).")
    threads: int = Field(0, ge=0, description="torch CPU threads (0 = torch's default); 1 avoids thread "
                         "thrashing on a small, shared CPU.")


# The modules whose code determines the matting network's trained weights (with all they import).
TRAINING_MODULES = ("stages.matte.training", "stages.matte.studio_data")


def _read_manifest(capture: CaptureOutput) -> dict[str, Any]:
    return capture.manifest(keys=("cameras", "frames", "width", "height"))


class FrameReader:
    """Reads a camera's linear frames, keeping the recent ones (guides are reused by 2 OLAT frames)."""

    def __init__(self, capture: CaptureOutput, cam: str, keep: int = 8) -> None:
        self.capture, self.cam, self.keep = capture, cam, keep
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()

    def path(self, index: int) -> Path:
        return self.capture.frame_path(self.cam, index)

    def exists(self, index: int) -> bool:
        return self.path(index).is_file()

    def read(self, index: int) -> np.ndarray:
        """The frame [H, W, 3] float32 linear."""
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        image = self.capture.frame(self.cam, index)[..., :3].astype(np.float32)
        self._cache[index] = image
        while len(self._cache) > self.keep:
            self._cache.popitem(last=False)
        return image


def usable_frames(manifest: dict[str, Any], reader: FrameReader) -> list[dict[str, Any]]:
    """Manifest frames that have an image for this camera (dropped frames have none)."""
    return [f for f in manifest["frames"] if f.get("status", "ok") != "dropped" and reader.exists(int(f["index"]))]


class CameraInputs:
    """Builds network inputs for one camera's frames (exposure reference from its F frames).

    ``statistics_frames``: only F frames with an index below it set the reference (None = all).
    """

    def __init__(self, manifest: dict[str, Any], capture: CaptureOutput, cam: str, inputs: InputConfig,
                 statistics_frames: int | None = None) -> None:
        self.reader = FrameReader(capture, cam)
        self.frames = usable_frames(manifest, self.reader)
        self.light = {int(f["index"]): f.get("light") for f in self.frames}
        self.guides = nearest_full_on(self.frames)
        self.statistics_frames = statistics_frames
        levels = [bright_level(self.reader.read(int(f["index"]))) for f in self.statistics_pool() if is_full_on(f)]
        self.reference = camera_reference(levels, inputs.exposure_floor)
        self.config = inputs

    def statistics_pool(self) -> list[dict[str, Any]]:
        """The frames that set this camera's reference and may feed SOC."""
        limit = self.statistics_frames
        return [f for f in self.frames if limit is None or int(f["index"]) < limit]

    def network_input(self, index: int) -> np.ndarray:
        """[6, H, W] input of frame ``index``."""
        image = self.reader.read(index)
        guide = self.reader.read(self.guides[index])
        olat = self.light[index] != "F"
        scale = olat_scale(image, self.reference, self.config.olat_floor_ratio) if olat else self.reference
        return network_input(image, scale, guide, self.reference)


def _image_scale(manifest: dict[str, Any], rig: RigConfig) -> float:
    """The capture's image size relative to the rig's sensor (its cameras' reference size)."""
    return round(float(manifest["width"]) / float(rig.width_px), 6)


def trained_model(ctx: StageContext, params: MatteParams, image_scale: float, device: str):
    """The supervised model from the shared cache, trained now if missing; returns (model, meta, cached)."""
    payload = {"train": params.train.model_dump(mode="json"), "data": params.data.model_dump(mode="json"),
               "image_scale": image_scale, "rig": params.rig.model_dump(mode="json")}
    key = cache_key(payload, training_code_digest(TRAINING_MODULES))

    def train() -> tuple[Any, dict[str, Any]]:
        start = time.perf_counter()
        jobs = identity_jobs(params.data, image_scale, params.rig)
        ctx.log.info("rendering matting training data: %d identities at scale %.4f", len(jobs), image_scale)
        train_set = collect(ctx.executor.map(render_identity, jobs, desc="matte training identities"))
        render_seconds = time.perf_counter() - start
        ctx.log.info("training the %s matting network on %d samples (%d iterations)", params.train.net_size,
                     len(train_set), params.train.iterations)
        with ctx.progress(params.train.iterations, "iterations") as progress:
            model, record = train_supervised(train_set, params.train, device, ctx.log,
                                             on_step=lambda step, parts: progress.advance(1, loss=parts["loss"]))
        return model, {"payload": payload, "render_seconds": render_seconds, "training": record}

    return load_or_train(ctx.shared_cache_dir, key, train, ctx.log)


def soc_inputs(cameras: dict[str, CameraInputs], count: int, seed: int) -> np.ndarray:
    """Network inputs [N, 6, H, W] of ``count`` frames spread over cameras, F and OLAT alike."""
    pairs = [(cam, int(f["index"])) for cam, ci in cameras.items() for f in ci.statistics_pool()]
    if count == 0 or not pairs:
        return np.zeros((0, 6, 1, 1), np.float32)
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(pairs), size=min(count, len(pairs)), replace=False)
    return np.stack([cameras[pairs[i][0]].network_input(pairs[i][1]) for i in sorted(picks)])


def adapted_model_dir(ctx: StageContext, model: Any) -> tuple[Path, str]:
    """Save the SOC-adapted model for the inference workers; returns (folder, weights digest).

    The folder is named by the digest of the weights, in the stage's cache (reused by a
    rerun that adapts to the same weights), written through a temporary sibling and renamed.
    """
    import shutil
    import tempfile

    from pipeline.hashing import hash_file
    from stages.matte.model_cache import MODEL_FILE, save_model

    root = ctx.cache_dir / "adapted_models"
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".adapted.", dir=root))
    save_model(staging, model, {})
    digest = hash_file(staging / MODEL_FILE)
    folder = root / digest
    if folder.is_dir():
        shutil.rmtree(staging, ignore_errors=True)
    else:
        try:
            staging.rename(folder)
        except OSError:  # stored meanwhile by another run
            shutil.rmtree(staging, ignore_errors=True)
    return folder, digest


def inference_items(cameras: dict[str, CameraInputs], params: MatteParams, device: str,
                    model_dir: Path | None, model_digest: str) -> list[tuple[str, int, Any]]:
    """(camera, frame index, ``MatteItem``) for every usable image, camera by camera."""
    from stages.matte.inference import MatteItem

    items = []
    for cam, ci in cameras.items():
        for frame in ci.frames:
            index = int(frame["index"])
            items.append((cam, index, MatteItem(
                image_path=str(ci.reader.path(index)), guide_path=str(ci.reader.path(ci.guides[index])),
                olat=ci.light[index] != "F", reference=float(ci.reference),
                olat_floor_ratio=float(params.train.inputs.olat_floor_ratio),
                model_dir=str(model_dir) if model_dir is not None else "", model_digest=model_digest,
                gate_low=params.gate_low, gate_high=params.gate_high, device=device, threads=params.threads,
                baseline=params.baseline if model_dir is None else None)))
    return items


def _without_timings(record: Any) -> Any:
    """``record`` (nested dicts and lists) without its ``seconds`` entries."""
    if isinstance(record, dict):
        return {k: _without_timings(v) for k, v in record.items() if k != "seconds"}
    if isinstance(record, list):
        return [_without_timings(v) for v in record]
    return record


def run(ctx: StageContext) -> None:
    """Matte every image of the capture."""
    from pipeline.itemcache import stage_item_cache
    from scene.image_io import write_png16
    from stages.matte.inference import matte_item, matte_item_key

    params: MatteParams = ctx.params  # type: ignore[assignment]
    if params.threads:
        import torch

        torch.set_num_threads(params.threads)
    capture = CaptureOutput(ctx.input("capture"))
    out = MatteOutput(ctx.out)
    manifest = _read_manifest(capture)
    device = resolve_device(params.device, "matte.device")
    cameras = {cam: CameraInputs(manifest, capture, cam, params.train.inputs, params.statistics_frames)
               for cam in manifest["cameras"]}
    record: dict[str, Any] = {"method": params.method, "device": device}
    model_dir, model_digest = None, "baseline"
    if params.method == "modnet":
        image_scale = _image_scale(manifest, params.rig)
        model, meta, cached = trained_model(ctx, params, image_scale, device)
        # model.json holds what decides the mattes (which model, its training and SOC records);
        # timings and whether the model came from the cache go to the metrics only, so a rerun
        # that mattes identically writes identical files and the stages below stay fresh.
        record.update({"model_key": meta.get("key"), "training": _without_timings(meta.get("training"))})
        ctx.metrics["model_cached"] = int(cached)
        ctx.metrics["training_seconds"] = 0.0 if cached else float(meta["training"]["seconds"])
        ctx.metrics["training_render_seconds"] = 0.0 if cached else float(meta.get("render_seconds") or 0.0)
        unlabelled = soc_inputs(cameras, params.soc_frames, params.soc.seed)
        model, soc_record = soc_adapt(model, unlabelled, params.soc, device)
        record["soc"] = _without_timings(soc_record)
        ctx.metrics["soc_seconds"] = float(soc_record["seconds"])
        model_dir, model_digest = adapted_model_dir(ctx, model)
        record["adapted_weights_digest"] = model_digest

    jobs = inference_items(cameras, params, device, model_dir, model_digest)
    written: dict[str, dict[int, Path]] = {cam: {} for cam in cameras}
    for cam in cameras:
        out.mattes_dir(cam).mkdir(parents=True, exist_ok=True)

    def write(position: int, result: dict) -> float:
        cam, index, _ = jobs[position]
        path = out.matte_path(cam, index)
        write_png16(path, np.asarray(result["alpha_u16"], np.float64) / 65535.0)  # exact: the same 16-bit values
        written[cam][index] = path
        return float(result["seconds"])

    cache = stage_item_cache(ctx)
    start = time.perf_counter()
    item_seconds = cache.map(ctx.executor, matte_item, [job[2] for job in jobs], matte_item_key, desc="images",
                             gpu=device.startswith("cuda"), consume=write)
    seconds = time.perf_counter() - start
    cache.report(ctx, "images", metrics_prefix="images")
    total = len(jobs)
    ctx.metrics["images"] = total
    ctx.metrics["inference_seconds"] = seconds
    # Throughput of the images matted by this run; when every image came from the cache, that of
    # the runs that matted them (their per-image seconds are kept with the results).
    if cache.misses and seconds > 0:
        ctx.metrics["images_per_second"] = cache.misses / seconds
    else:
        ctx.metrics["images_per_second"] = total / sum(item_seconds) if sum(item_seconds) > 0 else 0.0
    write_contact_sheet(out.contact_sheet_path, manifest, written, params.contact_sheet_frames)
    out.write_model_record(record)


STAGE = Stage(name="matte", inputs=("capture",), params=MatteParams, run=run,
              doc="Alpha matte per image: MODNet-style network trained on other studio subjects, SOC-adapted.")
