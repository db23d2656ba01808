"""ag2gs from Python: scenes, training with a callback, rendering to NumPy,
click and text queries, removal and simulation.

The module runs the same library as the `ag2gs` program, in this process:
a model trained here with the program's default settings and seed has the
program's bits, renders are the arrays `ag2gs render` writes, and queries
select the anchors `ag2gs query` selects. Cameras follow COLMAP: `R` and `t`
map world points to camera coordinates (x_cam = R x_world + t), x to the
right, y down, z forward; `fx, fy, cx, cy` in pixels of the camera's size.
See docs/python.md.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _ag2gs

__all__ = ["set_log_level", "devices", "read_image", "to_uint8", "Camera", "View", "Scene", "Model", "Selection", "train", "run", "Stopped"]

OUTPUTS = ("rgb", "depth", "alpha", "feature", "instance")


class Stopped(RuntimeError):
    """A run stopped by Ctrl-C; its checkpoint was written (continue with resume=True)."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status


def devices() -> List[Dict[str, Any]]:
    """The OpenCL devices, as `ag2gs devices` lists them (index, name, platform, type, ...)."""
    return _ag2gs.devices()


def set_log_level(level: str) -> None:
    """Messages printed outside commands (queries, renders): debug, info, warn (default), error or off.
    Commands run by train/run log as the program does (quiet=True for warnings only)."""
    _ag2gs.set_log_level(level)


def read_image(path: Union[str, os.PathLike]) -> np.ndarray:
    """An image file (PNG, JPEG, ...) as HxWx3 uint8 RGB, read as the program reads it."""
    return _ag2gs.read_image(os.fspath(path))


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """A float RGB render as the 8-bit pixels `ag2gs render` writes to its PNGs."""
    x = np.clip(np.nan_to_num(np.asarray(rgb, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0), 0, 1)
    return np.floor((x * np.float32(255)).astype(np.float64) + 0.5).astype(np.uint8)


def run(*args: str, callback: Optional[Callable[[Dict[str, Any]], Any]] = None) -> int:
    """Runs one `ag2gs` command line in this process, e.g. run("info", "out/model").

    Errors raise ValueError (bad arguments), FileNotFoundError (a missing
    file or folder) or RuntimeError, with the program's message. Returns 0,
    or the status of a run stopped by a signal or by the callback."""
    return _ag2gs.run([str(a) for a in args], callback)


@dataclass
class Camera:
    """A pinhole camera: COLMAP's world-to-camera R (3x3) and t (3), intrinsics in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray
    t: np.ndarray
    name: str = ""

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def size(self) -> Tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    @property
    def center(self) -> np.ndarray:
        """The camera's position in world coordinates (-R^T t)."""
        return -np.asarray(self.R).T @ np.asarray(self.t)

    def scaled(self, factor: int) -> "Camera":
        """The camera at 1/factor resolution, as `-r factor` scales the scene's cameras."""
        return Camera._from(_ag2gs.scale_camera(self, int(factor)))

    def resized(self, width: int, height: int) -> "Camera":
        """The same view rendered at width x height pixels (intrinsics scaled with the size)."""
        return Camera._from(_ag2gs.resize_camera(self, int(width), int(height)))

    @staticmethod
    def _from(d: Dict[str, Any]) -> "Camera":
        return Camera(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"], np.asarray(d["R"]),
                      np.asarray(d["t"]), d["name"])


@dataclass
class View:
    """One image of a scene: its camera at the loaded resolution and its pixels."""

    index: int
    name: str
    stem: str
    test: bool
    camera: Camera
    _scene: "Scene" = field(repr=False)

    @property
    def image(self) -> np.ndarray:
        """HxWx3 uint8, at the camera's size (read on first use, cached by the scene)."""
        return self._scene._core.image(self.index)


class Scene:
    """A scene folder (images/, sparse/0/, optional SAM masks and CLIP features).

    resolution divides every camera (as -r); eval holds out every 8th view
    (as --eval) or the named test_images."""

    def __init__(self, path: Union[str, os.PathLike], resolution: int = 1, eval: bool = False,
                 sparse: str = "", test_images: Sequence[str] = ()):
        if resolution < 1:
            raise ValueError(f"resolution must be >= 1 (it divides the camera resolution), not {resolution}")
        self.path = os.fspath(path)
        self.resolution = resolution
        self.eval = eval or bool(test_images)
        self.sparse = sparse
        self._core = _ag2gs._Scene(self.path, resolution, self.eval, sparse, list(test_images))
        self.views = [View(d["index"], d["name"], d["stem"], d["test"], Camera._from(d["camera"]), self)
                      for d in self._core.views()]

    @property
    def train_views(self) -> List[View]:
        return [v for v in self.views if not v.test]

    @property
    def test_views(self) -> List[View]:
        return [v for v in self.views if v.test]

    def view(self, name: str) -> View:
        """The view called `name` (the image name, its stem, or the name without extension)."""
        for v in self.views:
            if name in (v.name, v.stem, os.path.splitext(v.name)[0]):
                return v
        raise KeyError(f"{self.path}: no view '{name}'")

    def _flags(self) -> List[str]:
        f = ["-r", str(self.resolution)]
        if self.sparse:
            f += ["--sparse", self.sparse]
        return f

    def __repr__(self) -> str:
        return f"Scene({self.path!r}, {len(self.views)} views, resolution={self.resolution})"


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _settings(settings: Dict[str, Any]) -> List[str]:
    """Keyword settings as the program's flags: iters=2000 -> --iters 2000,
    far_shell=False -> --far-shell=false, eval=True -> --eval=true, stages=(1, 2) -> --stages 1,2."""
    args: List[str] = []
    for k, v in settings.items():
        if v is None:
            continue
        if isinstance(v, bool):  # flags and true/false options alike take --name=true|false
            args.append(f"{_flag(k)}={'true' if v else 'false'}")
        elif isinstance(v, (list, tuple)):
            args += [_flag(k), ",".join(str(x) for x in v)]
        else:
            args += [_flag(k), str(v)]
    return args


def _scene_args(scene: Union["Scene", str, os.PathLike]) -> Tuple[str, List[str]]:
    if isinstance(scene, Scene):
        flags = scene._flags()
        if scene.eval:
            flags.append("--eval")
        return scene.path, flags
    return os.fspath(scene), []


def train(scene: Union[Scene, str, os.PathLike], out: Union[str, os.PathLike],
          callback: Optional[Callable[[int, Dict[str, Any]], Any]] = None, device: Optional[int] = None,
          **settings: Any) -> "Model":
    """Trains stages 1-3 as `ag2gs train SCENE -o OUT` does, with the same settings
    table: every flag of `ag2gs train --help` as a keyword (iters=2000, seed=1,
    stages=(1, 2), preset="paper", force=True, resume=True, ...).

    callback(iteration, metrics) runs after every iteration; metrics holds
    iteration, iterations, stage, loss, psnr, l1, ssim, anchors, gaussians
    and eta_s. Returning False stops the run as Ctrl-C does: the iteration
    finishes, the checkpoint is written, and Stopped is raised (continue with
    resume=True). Returns the trained Model."""
    path, flags = _scene_args(scene)
    if "resolution" in settings:
        flags = [f for i, f in enumerate(flags) if f != "-r" and (i == 0 or flags[i - 1] != "-r")]
    args = ["train", path, "-o", os.fspath(out)] + flags + _settings(settings)
    if device is not None:
        args += ["--device", str(device)]
    hook = None
    if callback is not None:
        def hook(m: Dict[str, Any]) -> Any:
            return callback(m["iteration"], m)
    status = _ag2gs.run(args, hook)
    if status:
        raise Stopped(f"training stopped; checkpoint in {os.fspath(out)} (continue with resume=True)", status)
    return Model.load(out, device=device)


def _with_help(doc: Optional[str], command: str, how: str) -> str:
    """A docstring followed by the program's --help of `command`, whose flags are the keywords."""
    try:
        text = _ag2gs.command_help(command)
    except Exception:  # the docstring must never stop the import
        return doc or ""
    return (doc or "") + f"\n\n    {how}\n\n" + "\n".join("    " + line for line in text.splitlines())


train.__doc__ = _with_help(train.__doc__, "train",
                           "The settings: every flag below as a keyword (--iters 2000 is iters=2000).")


class Selection:
    """Anchors of a model chosen by a query: ids, and masks in any camera."""

    def __init__(self, model: "Model", anchors: Iterable[int], record: Optional[Dict[str, Any]] = None):
        self.model = model
        self.anchors = np.asarray(sorted(int(a) for a in anchors), dtype=np.int32)
        self.record = record or {}

    def mask(self, camera: Camera) -> np.ndarray:
        """HxW bool: the pixels of the selection in `camera`, as `ag2gs query` writes its masks."""
        return self.model._query_engine(None).mask(camera, self.anchors.tolist())

    def save(self, path: Union[str, os.PathLike]) -> str:
        """Writes a selection.json that `ag2gs remove/simulate --selection` read."""
        record = dict(self.record)
        record["anchors"] = self.anchors.tolist()
        record.setdefault("model", os.path.join(self.model.path, "model.ag2gs"))
        # Whole or not at all, as the program writes its files: a temporary
        # name beside the target, renamed into place.
        path = os.fspath(path)
        tmp = f"{path}.tmp.{os.getpid()}"
        try:
            with open(tmp, "w") as f:
                json.dump(record, f)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
        return path

    def __len__(self) -> int:
        return len(self.anchors)

    def __repr__(self) -> str:
        return f"Selection({len(self.anchors)} anchors of {self.model.path!r})"


class Model:
    """A model folder written by `ag2gs train` (model.ag2gs, point_cloud.ply)."""

    def __init__(self, path: str, device: Optional[int] = None):
        self.path = path
        self.device = -1 if device is None else device
        self._renderers: Dict[Tuple[Tuple[str, ...], Any], Any] = {}
        self._queries: Dict[Any, Any] = {}
        self._scene: Optional[Scene] = None

    @staticmethod
    def load(path: Union[str, os.PathLike], device: Optional[int] = None) -> "Model":
        path = os.fspath(path)
        if not os.path.isdir(path):
            raise FileNotFoundError(f"{path}: no such model folder (a folder written by `ag2gs train`)")
        if not os.path.exists(os.path.join(path, "model.ag2gs")) and not os.path.exists(
                os.path.join(path, "point_cloud.ply")):
            raise FileNotFoundError(f"{path}: holds no model.ag2gs or point_cloud.ply; is it a model folder "
                                    "written by `ag2gs train`?")
        return Model(path, device)

    @property
    def metrics(self) -> Dict[str, Any]:
        """metrics.json of the run that trained it (empty when absent)."""
        p = os.path.join(self.path, "metrics.json")
        if not os.path.exists(p):
            return {}
        with open(p) as f:
            return json.load(f)

    def render(self, camera: Camera, outputs: Sequence[str] = ("rgb",),
               background: Optional[Sequence[float]] = None) -> Dict[str, np.ndarray]:
        """Renders `camera` into arrays: rgb float32 HxWx3 (over the learned sky
        unless a background is given), depth HxW (mean depth, 0 where empty),
        alpha HxW, feature HxWx3, instance HxW int32 (cluster ids, -1 = none)."""
        if isinstance(outputs, str):
            outputs = (outputs,)
        outputs = tuple(outputs)
        for o in outputs:
            if o not in OUTPUTS:
                raise ValueError(f"outputs: unknown output '{o}'; choose from rgb,depth,alpha,feature,instance")
        if not outputs:
            raise ValueError("outputs is empty; choose from rgb,depth,alpha,feature,instance")
        if not isinstance(camera, Camera):
            raise TypeError("camera must be an ag2gs.Camera (scene.views[i].camera)")
        bg = None if background is None else tuple(float(x) for x in background)
        key = (outputs, bg)
        if key not in self._renderers:
            self._renderers[key] = _ag2gs._Renderer(self.path, "", list(outputs), bg, self.device)
        return self._renderers[key].render(camera)

    def _query_engine(self, scene: Optional[Scene], with_language: bool = False):
        if scene is not None:
            self._scene = scene
        if self._scene is None:
            raise ValueError("the model has no scene yet: give scene= to the first query")
        key = (id(self._scene), with_language)
        if key not in self._queries:
            # A text query needs the language features; a click or a mask does not.
            if not with_language and (id(self._scene), True) in self._queries:
                return self._queries[(id(self._scene), True)]
            self._queries[key] = _ag2gs._Query(self.path, self._scene._core, with_language, self.device)
        return self._queries[key]

    def query(self, text: Optional[str] = None, vocab: Optional[str] = None,
              click: Optional[Tuple[str, float, float]] = None, scene: Optional[Scene] = None,
              text_embedding: Optional[str] = None, click_by: str = "auto") -> Selection:
        """Selects an object as `ag2gs query` does: by text (a phrase of the vocab
        JSON, or a .npy embedding) or by a click (view name, x, y in the pixels of
        the full-size image). The scene defaults to the one given before."""
        if scene is None and self._scene is None:
            scene = Scene(self._training_scene(), resolution=self._training_resolution(), eval=True)
        by_text = text is not None or text_embedding is not None
        engine = self._query_engine(scene, with_language=by_text)
        view, xy = "", ""
        if click is not None:
            if len(click) != 3:
                raise ValueError("click must be (view name, x, y)")
            view, xy = str(click[0]), f"{click[1]},{click[2]}"
        anchors, record = engine.run(view, xy, text or "", os.fspath(vocab) if vocab else "",
                                     os.fspath(text_embedding) if text_embedding else "", click_by)
        return Selection(self, anchors, json.loads(record))

    def _training_scene(self) -> str:
        scene = self.metrics.get("scene")
        if not scene:
            raise ValueError("give scene=: the model's metrics.json does not name its scene")
        return scene

    def _training_resolution(self) -> int:
        return int(self.metrics.get("resolution", 1))

    def _selection_file(self, sel: Selection, folder: str) -> str:
        path = os.path.join(folder, "selection.json")
        sel.save(path)
        return path

    def _apply(self, command: str, sel: Selection, scene: Union[Scene, str, os.PathLike],
               out: Union[str, os.PathLike], settings: Dict[str, Any]) -> str:
        """Runs remove or simulate on the selection (written to a temporary selection.json)."""
        path, _ = _scene_args(scene)
        with tempfile.TemporaryDirectory() as tmp:
            f = self._selection_file(sel, tmp)
            self._run([command, self.path, "--scene", path, "-o", os.fspath(out), "--selection", f] +
                      _settings(settings))
        return os.fspath(out)

    def remove(self, sel: Selection, scene: Union[Scene, str, os.PathLike], out: Union[str, os.PathLike],
               **settings: Any) -> "Model":
        """`ag2gs remove`: the model without the selection (holes filled), written to out."""
        return Model.load(self._apply("remove", sel, scene, out, settings),
                          self.device if self.device >= 0 else None)

    def simulate(self, sel: Selection, scene: Union[Scene, str, os.PathLike], out: Union[str, os.PathLike],
                 **settings: Any) -> str:
        """`ag2gs simulate`: the selection as a physical object (frames=30, material=..., as the flags)."""
        return self._apply("simulate", sel, scene, out, settings)

    def _run(self, args: List[str]) -> None:
        if self.device >= 0:
            args = args + ["--device", str(self.device)]
        status = _ag2gs.run(args, None)
        if status:
            raise Stopped(f"{args[0]} stopped before it wrote {args[args.index('-o') + 1]}", status)

    def __repr__(self) -> str:
        return f"Model({self.path!r})"


Model.remove.__doc__ = _with_help(Model.remove.__doc__, "remove", "Keywords: the flags of `ag2gs remove` below.")
Model.simulate.__doc__ = _with_help(Model.simulate.__doc__, "simulate",
                                    "Keywords: the flags of `ag2gs simulate` below.")
