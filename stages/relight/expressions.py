"""Novel expressions: blendshape curves (ARKit-named CSV) or OBJ meshes -> head-space meshes via the actor rig.

The actor rig is the capture's scan session (``capture/scans/scans.npz``: neutral first, then
FACS poses; ``mesh(w) = neutral + sum_k w_k (scan_k - neutral)``). A CSV row of ARKit weights
(``eyeBlinkLeft``, ``jawOpen`` ... as face-capture apps export them; a ``frame``/``time``
column is ignored) drives the generic ICT blendshapes (whose names are ARKit's with ``_L``/
``_R``), and the resulting offset is projected onto the actor rig's poses (least squares,
weights clipped to [0, 1]): the head does what this actor can do, with the actor's own shapes.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from stages.capture.output import CaptureOutput

_IGNORED_COLUMNS = {"frame", "time", "timecode", "time_s", "blendshapecount", "index"}


def load_actor_rig(capture: CaptureOutput) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Pose names [K], neutral [V, 3] and offsets [K, V, 3] (metres) from the capture's scan session."""
    data = capture.scans(keys=("names", "vertices"))
    names = [str(n) for n in data["names"]]
    verts = np.asarray(data["vertices"], np.float64)
    return names[1:], verts[0], verts[1:] - verts[0]


def arkit_to_ict(name: str) -> str:
    """``eyeBlinkLeft`` -> ``eyeBlink_L`` (ARKit suffixes to ICT's); other names unchanged."""
    return re.sub(r"Left$", "_L", re.sub(r"Right$", "_R", name.strip()))


def read_weights_csv(path: Path, ict_names: tuple[str, ...]) -> np.ndarray:
    """ICT weights [F, E] from an ARKit-named CSV; unknown names raise ``ValueError`` listing them."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: cannot read the blendshape CSV ({err})") from err
    if len(rows) < 2:
        raise ValueError(f"{path}: the blendshape CSV needs a header row and at least one row of weights")
    header = [h.strip() for h in rows[0]]
    index = {n.lower(): i for i, n in enumerate(ict_names)}
    columns, unknown = [], []
    for j, name in enumerate(header):
        if name.lower() in _IGNORED_COLUMNS or not name:
            continue
        key = arkit_to_ict(name).lower()
        if key not in index:
            unknown.append(name)
        else:
            columns.append((j, index[key]))
    if unknown:
        raise ValueError(f"{path}: unknown blendshape names {unknown}; expected ARKit names such as "
                         f"jawOpen, eyeBlinkLeft, mouthSmileRight (known: "
                         f"{', '.join(sorted({re.sub('_L$', 'Left', re.sub('_R$', 'Right', n)) for n in ict_names}))})")
    weights = np.zeros((len(rows) - 1, len(ict_names)))
    for i, row in enumerate(rows[1:]):
        for j, k in columns:
            try:
                weights[i, k] = float(row[j])
            except (IndexError, ValueError) as err:
                raise ValueError(f"{path}: row {i + 2}, column '{header[j]}': not a number ({err})") from err
    if not np.isfinite(weights).all():
        raise ValueError(f"{path}: NaN or infinite weights")
    return weights


def meshes_from_weights(ict_weights: np.ndarray, ict_deltas_m: np.ndarray, neutral_m: np.ndarray,
                        rig_offsets_m: np.ndarray) -> np.ndarray:
    """Head-space meshes [F, V, 3]: generic ICT offsets projected onto the actor rig's poses."""
    basis = rig_offsets_m.reshape(len(rig_offsets_m), -1).T  # [3V, K]
    out = []
    for w in ict_weights:
        target = np.tensordot(w, ict_deltas_m, axes=1).reshape(-1)  # [3V]
        coeffs, *_ = np.linalg.lstsq(basis, target, rcond=None)
        out.append(neutral_m + (basis @ np.clip(coeffs, 0.0, 1.0)).reshape(-1, 3))
    return np.asarray(out, np.float32)


def read_obj_vertices(path: Path, num_vertices: int) -> np.ndarray:
    """Vertices [V, 3] of an OBJ in the rig's topology (metres, head space)."""
    verts = []
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith("v "):
                verts.append([float(v) for v in line.split()[1:4]])
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: cannot read OBJ vertices ({err})") from err
    if len(verts) != num_vertices:
        raise ValueError(f"{path}: has {len(verts)} vertices, the actor rig has {num_vertices}; the OBJ must use "
                         "the tracked mesh's topology")
    return np.asarray(verts, np.float32)


def read_obj_sequence(folder: Path, num_vertices: int) -> np.ndarray:
    """All ``*.obj`` of a folder in name order -> [F, V, 3]."""
    files = sorted(Path(folder).glob("*.obj"))
    if not files:
        raise ValueError(f"{folder}: no .obj files")
    return np.stack([read_obj_vertices(f, num_vertices) for f in files])
