"""The map server's component: holds maps and answers map requests; no sockets, clock passed in.

A map is a finished run's folder (:class:`~gsfix_online.services.run_folder.RunFolder`:
its 3DGS model, TSDF mesh, view cameras, GSFixer checkpoints and fallback choice) or, in a live
graph, the splat node's latest export and the TSDF node's latest mesh. ``nodes/map_server.py``
puts it on a ZeroMQ socket (``gsfix-online serve RUN_DIR``); :mod:`gsfix_online.apps.client`
is the client and documents the protocol.

Requests (``op``, ``args``) and what :meth:`MapServer.handle` returns (result, buffers):

- ``maps``: the maps with their versions; ``stats``: counters and whether a repair runs;
- ``mesh`` (map, fmt ply | glb), ``splats`` (map), ``image`` (map, path): a file's bytes;
- ``views`` (map): keyframe and view cameras;
- ``render`` (map, T_world_cam [16], K [9], width, height, source gs | mesh | both).

``repair`` is long: :meth:`MapServer.begin_repair` checks the request (on the caller's thread, no
rendering: a refused request costs nothing), :meth:`RepairJob.run` renders the view, runs GSFixer,
applies the run's fallback choice and distils the result into a copy of the Gaussian map (on a
worker thread; it reads the served map and writes only its own copy, so the caller's thread keeps
answering, progress included, however long a render takes on a loaded machine), and
:meth:`MapServer.finish_repair` swaps the copy in and bumps the version. One
repair at a time: another while one runs is answered ``busy`` (no queue: a client decides
whether to ask again, and nothing waits unseen behind a long job).

Every bad request raises :class:`RequestError` with a kind and one line: a pose with NaN or a
rotation that is not orthonormal, intrinsics that do not fit the size, a size above
``max_pixels``, an unknown map or op, a path outside the run folder.
"""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import tempfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from gsfix_online.core.config import profile, rng
from gsfix_online.core.types import FrameError, Intrinsics, check_pose
from gsfix_online.fixer.config import FixerConfig
from gsfix_online.mapping.mesh_planes import PlaneGuessConfig
from gsfix_online.mapping.splat.mapper import DensifyConfig, MapperConfig
from gsfix_online.repair.compose import ComposeRules
from gsfix_online.repair.ref_warp import RefWarpConfig
from gsfix_online.services.run_folder import Keyframe, RunFolder, RunFolderError, read_keyframes

logger = logging.getLogger(__name__)

SOURCES = ("gs", "mesh", "both")
MESH_FORMATS = ("ply", "glb")
Progress = Callable[[float, str], None]


class RequestError(ValueError):
    """A request the server refuses; ``kind`` is one of the client's error kinds."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class ServerConfig(ComposeRules):  # a repair is composed as the repair node composes it
    max_pixels: int = field(
        default=4096 * 4096, metadata=rng(1, None, "largest width x height of a render or repair")
    )
    # GSFixer: the run's newest checkpoint (work/checkpoints/latest) when it has one, else
    # fixer.model (path "" = the packaged base). It repairs as the repair node does
    # (configs/profiles/repair_cpu.yaml).
    fixer: FixerConfig = field(default_factory=lambda: profile(FixerConfig, "repair_cpu.yaml"))
    use_run_checkpoint: bool = True
    # Distillation of a repair (mapper.distill_iters steps; 0 = deliver the repair only)
    mapper: MapperConfig = field(
        default_factory=lambda: MapperConfig(densify=DensifyConfig(enabled=False))
    )
    seed_empty: bool = True  # seed Gaussians where no map holds anything (repairer.seed_depth)
    # the surface guessed there, as the TSDF node guesses it for the repair graph
    guess: PlaneGuessConfig = field(default_factory=PlaneGuessConfig)
    # The run's input keyframes (work/keyframes) warped into the view, as the planner warps
    # its reference frames (the fallback ref_inpaint); a live map, or a run without them, has
    # none, and ref_inpaint is mesh_inpaint there
    reference_capacity: int = field(default=200, metadata=rng(1, None, "reference frames kept"))
    ref_warp: RefWarpConfig = field(default_factory=RefWarpConfig)


@dataclass
class ServedMap:
    """One map and its caches; ``version`` counts the repairs distilled into it."""

    name: str
    run: RunFolder | None  # None: a live map (the splat node's export, the TSDF node's mesh)
    gmap: Any  # GaussianMap
    keyframes: list[Keyframe]
    ply_path: Path | None  # the 3DGS PLY on disk while version has not changed it
    mesh_path: Path | None
    version: int = 0
    mesh_version: int = 0
    renderer: Any = None  # Mapper around gmap, rebuilt when gmap changes
    cache: dict[str, tuple[int, Any]] = field(default_factory=dict)  # key -> (version, value)

    def cached(self, key: str, version: int, make: Callable[[], Any]) -> Any:
        """``make()``'s value for this version; a repair's worker and the request thread may
        both make it once (each gets a whole one; the later stays)."""
        hit = self.cache.get(key)
        if hit is None or hit[0] != version:
            hit = (version, make())
            self.cache[key] = hit
        return hit[1]

    @property
    def has_mesh(self) -> bool:
        return self.mesh_path is not None and self.mesh_path.is_file()

    def mesh(self) -> Any:
        """The map's mesh (a TriMesh), checked once per version: a run's must be whole and have
        triangles, a live TSDF node's snapshot may still be empty; a damaged file is refused."""
        from gsfix_online.mapping.mesh import MeshFormatError, read_mesh

        if not self.has_mesh:
            raise RequestError("not_found", f"map {self.name!r} has no mesh")
        assert self.mesh_path is not None
        path = self.mesh_path

        def load() -> Any:
            try:
                return read_mesh(path, allow_empty=self.run is None)
            except MeshFormatError as exc:
                raise RequestError("failed", str(exc)) from None

        return self.cached("mesh", self.mesh_version, load)


def wrap_map(gmap: Any, cfg: MapperConfig, scene_scale_m: float = 1.0) -> Any:
    """A :class:`Mapper` around an existing GaussianMap (renders, distillation)."""
    from gsfix_online.mapping.splat.mapper import Mapper

    mapper = Mapper(dataclasses.replace(cfg, sh_degree=gmap.sh_degree), gmap.channels, gmap.device)
    mapper.gmap = gmap
    mapper.scene_scale = float(scene_scale_m)
    # The optimizers were built around the empty map of the constructor: rebuild them around
    # this one (the Mapper itself does the same when it loads a snapshot).
    mapper._build_optimizers()
    return mapper


def _rgb8(color: npt.NDArray[np.float32]) -> npt.NDArray[np.uint8]:  # [H, W, C] 0..1 -> [H, W, 3]
    out = np.rint(np.clip(color, 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.repeat(out, 3, axis=2) if out.shape[2] == 1 else out


def _numbers(args: dict[str, Any], key: str, n: int) -> npt.NDArray[np.float64]:
    v = args.get(key)
    if not isinstance(v, list | tuple) or len(v) != n:
        got = f"{len(v)} values" if isinstance(v, list | tuple) else type(v).__name__
        raise RequestError("bad_request", f"{key} must be {n} numbers, got {got}")
    if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
        raise RequestError("bad_request", f"{key} must be {n} numbers")
    return np.asarray(v, dtype=np.float64)


def _size(args: dict[str, Any]) -> tuple[int, int]:
    w, h = args.get("width"), args.get("height")
    for name, v in (("width", w), ("height", h)):
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise RequestError("bad_request", f"{name} must be a positive int, got {v!r}")
    return int(w), int(h)  # type: ignore[arg-type]


def _choice(name: str, value: Any, allowed: tuple[str, ...]) -> str:
    if value not in allowed:
        raise RequestError(
            "bad_request", f"{name} must be one of {', '.join(allowed)}, got {value!r}"
        )
    return str(value)


@dataclass
class _View:
    T_world_cam: npt.NDArray[np.float64]  # [4, 4]
    intrinsics: Intrinsics


@dataclass
class RepairJob:
    """One repair: a checked view in; its renders, the repair and the distilled map copy out."""

    map: ServedMap
    view: _View
    server: MapServer
    started: float
    gs: npt.NDArray[np.uint8] | None = None  # [H, W, 3]; the renders, made by run()
    alpha: npt.NDArray[np.float32] | None = None  # [H, W]
    mesh: npt.NDArray[np.uint8] | None = None  # [H, W, 3]
    mesh_depth: npt.NDArray[np.float32] | None = None  # [H, W] m, 0 = no surface
    valid: npt.NDArray[np.bool_] | None = None  # [H, W] the mesh has a surface there
    guessed: npt.NDArray[np.float32] | None = None  # [H, W] m, the planes' guess off the mesh
    result: dict[str, Any] = field(default_factory=dict)
    image: npt.NDArray[np.uint8] | None = None
    new_gmap: Any = None  # the distilled copy, swapped in by finish_repair

    def render(self) -> None:
        """The view's 3DGS and mesh renders. The 3DGS one goes through a renderer of its own,
        so it shares only the served map's tensors (read, never written) with the requests the
        caller's thread answers meanwhile; mesh ray casting is read-only."""
        m, v = self.map, self.view
        self.gs, _, self.alpha = self.server.render_gs(m, v, shared=False)
        r = self.server.render_mesh(m, v)
        self.mesh, self.mesh_depth, self.valid = r.rgb(), r.depth_m, r.valid
        self.guessed = self.server.guess_depth(m, v, r.valid)

    def run(self, progress: Progress) -> None:
        """Renders, GSFixer, the fallback choice, distillation (on a copy of the map). Runs on a
        worker beside the server's other requests: it writes only the job and its own copy."""
        from gsfix_online.mapping.splat.gaussians import GaussianMap
        from gsfix_online.repair.compose import compose_view
        from gsfix_online.repair.fallback import baseline_candidates
        from gsfix_online.repair.repairer import seed_depth

        cfg = self.server.cfg
        # 0. The view's renders (seconds at a large size on a loaded CPU)
        progress(0.0, "rendering the view (3DGS and mesh)")
        self.render()
        assert self.gs is not None and self.alpha is not None and self.mesh is not None
        assert self.mesh_depth is not None and self.valid is not None
        progress(0.05, "the view is rendered; repairing it")
        # 1. The model (loaded once, on the first repair)
        repairer = self.server.repairer_for(self.map, progress)
        # 2. GSFixer on the 3DGS and mesh renders
        progress(0.3, f"GSFixer ({cfg.fixer.inference.steps} DDIM steps)")
        out = repairer.repair(self.gs, self.mesh)
        # 3. The choice per region the run's repairs followed at this view's distance
        #    (GSFixer everywhere when it recorded none) and the composition (compose_view)
        thr = cfg.fixer.masks.alpha_threshold
        v = self.view
        refs = self.server.references_for(self.map, progress)
        warp = None if refs is None else refs.warp(v.intrinsics.K, v.T_world_cam,
                                                   self.mesh_depth, self.valid, cfg.ref_warp)  # fmt: skip
        cands = baseline_candidates(self.gs, self.alpha, self.mesh, self.valid, thr,
                                    None if warp is None else warp.image,
                                    None if warp is None else warp.valid)  # fmt: skip
        cands["fixed"] = out.image
        near, reach, trainer = self.server.choices_for(self.map)
        legacy = self.map.run is not None and not self.map.run.records_choices
        dist = (  # a run before it named repaired views apart: its cameras are no distance
            None if legacy
            else self.server.keyframe_distance(self.map, self.view, self.mesh_depth, self.valid)
        )  # fmt: skip
        synth = self.server.synthesised(self.map, self.view)
        done = compose_view(cands, self.alpha, self.valid, thr, dist, near, reach, trainer,
                            cfg.rules(), synth)  # fmt: skip
        image, choice = done.image, done.choice
        source = "run's recorded choice (at any distance: an older run)" if legacy else done.source
        self.image = image
        per_region = ", ".join(f"{r}={c}" for r, c in choice.describe().items())
        what = (
            "the packaged base" if out.model_version == 0 else f"checkpoint step {out.model_step}"
        )
        far = "" if dist is None else f" at {dist:.2f} m from the keyframes"
        reason = f"GSFixer ({what}); per region {per_region}, from the {source}{far}"
        if refs is None or not len(refs):
            reason += "; no reference frames (ref_inpaint is mesh_inpaint)"
        else:
            cover = 0.0 if warp is None else warp.coverage
            reason += f"; {len(refs)} reference frames warped over {100 * cover:.0f} % of the view"
        # 4. Distil into a copy of the map: readers keep the old version until it is swapped in
        iters = cfg.mapper.distill_iters
        if iters > 0:
            progress(0.6, f"distilling into map {self.map.name!r} ({iters} steps)")
            copy = GaussianMap.from_state_dict(self.map.gmap.state_dict(), self.map.gmap.device)
            depths = self.mesh_depth[self.valid]
            scale = cfg.mapper.scene_scale_m or (float(np.median(depths)) if depths.size else 1.0)
            mapper = wrap_map(copy, cfg.mapper, scale)
            seed = seed_depth(self.mesh_depth, self.valid, cfg.seed_empty, self.guessed)
            mask = done.mask
            res = mapper.distill(image, self.view.T_world_cam, self.view.intrinsics.K,
                                 iters=iters, mask=mask, depth=seed, observed=self.valid)  # fmt: skip
            self.new_gmap = mapper.gmap
            reason += (f"; distilled in {iters} steps (loss {res.loss_first:.4f} -> "
                       f"{res.loss_last:.4f}), {len(mapper.gmap)} Gaussians")  # fmt: skip
        else:
            reason += "; not distilled (mapper.distill_iters = 0)"
        self.result = {"reason": reason, "model_step": out.model_step,
                       "reference_coverage": 0.0 if warp is None else warp.coverage}  # fmt: skip
        progress(1.0, "done")


class MapServer:
    """Maps by name and the answers to requests (see the module docstring)."""

    def __init__(self, cfg: ServerConfig, started: float) -> None:
        self.cfg = cfg
        self.started = started
        self.maps: dict[str, ServedMap] = {}
        self.counts: Counter[str] = Counter()
        self.by_op: Counter[str] = Counter()
        self.job: RepairJob | None = None
        self._repairers: dict[str, Any] = {}  # map name -> ViewRepairer
        self._choices: dict[str, Any] = {}  # map name -> choices_for's (near, reach, trainer)
        self._references: dict[str, Any] = {}  # map name -> references_for's ReferenceStore
        self._keyframe_poses: dict[str, list[Any]] = {}  # map name -> RunFolder.keyframe_poses

    # -- maps --------------------------------------------------------------------------------

    def add_run(self, path: str | Path, name: str | None = None) -> ServedMap:
        """Serve a finished run's folder; RunFolderError when it is not one."""
        run = RunFolder(path)
        name = name or run.path.resolve().name
        if name in self.maps:
            raise RunFolderError(f"{path}: a map named {name!r} is served already")
        model = run.splat_model()
        mesh = run.mesh()  # checked before it is served: a damaged mesh is refused here
        m = ServedMap(name, run, model.gmap, run.keyframes, model.ply_path, run.mesh_path)
        if mesh is not None:
            m.cache["mesh"] = (m.mesh_version, mesh)
        self.maps[name] = m
        logger.info("map %r: %s, %d Gaussians, %d views, %d keyframes, mesh %s", name, run.path,
                    len(m.gmap), len(run.views), len(m.keyframes),
                    "yes" if m.has_mesh else "no")  # fmt: skip
        return m

    def update_splats(self, name: str, model_dir: str | Path) -> ServedMap:
        """A new Gaussian map for ``name`` (a live graph's export folder): a new version."""
        from gsfix_online.mapping.splat.ply import load_model

        model = load_model(model_dir)
        kfs = read_keyframes(Path(model_dir))
        m = self.maps.get(name)
        if m is None:
            m = self.maps[name] = ServedMap(name, None, model.gmap, kfs, model.ply_path, None)
        else:
            m.gmap, m.keyframes, m.ply_path = model.gmap, kfs, model.ply_path
            m.version += 1
            m.renderer = None
        return m

    def update_mesh(self, name: str, path: str | Path) -> None:
        """A new TSDF mesh for ``name`` (a live graph's mesh announcement)."""
        m = self.maps.get(name)
        if m is None:
            raise RequestError("unknown_map", f"no map {name!r} for the mesh {path}")
        m.mesh_path = Path(path)
        m.mesh_version += 1

    def get(self, name: Any) -> ServedMap:
        if name is None:
            if len(self.maps) != 1:
                names = ", ".join(self.maps) or "none yet"
                raise RequestError("unknown_map", f"name a map: the server holds {names}")
            return next(iter(self.maps.values()))
        if name not in self.maps:
            names = ", ".join(self.maps) or "none yet"
            raise RequestError("unknown_map", f"unknown map {name!r} (serving: {names})")
        return self.maps[name]

    @property
    def busy(self) -> bool:
        return self.job is not None

    # -- requests ----------------------------------------------------------------------------

    def handle(
        self, op: str, args: dict[str, Any], now: float
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """(result, buffers) of a quick request; raises RequestError."""
        handlers = {
            "maps": lambda: self.list_maps(),
            "stats": lambda: self.stats(now),
            "mesh": lambda: self.mesh_bytes(args),
            "splats": lambda: self.splat_bytes(args),
            "views": lambda: self.views(args),
            "image": lambda: self.image(args),
            "render": lambda: self.render(args),
        }
        if op not in handlers:
            known = ", ".join([*handlers, "repair"])
            raise RequestError("unknown_op", f"unknown request {op!r} (known: {known})")
        return handlers[op]()

    def count(self, op: str, ok: bool) -> None:
        self.counts["requests"] += 1
        self.by_op[op] += 1
        if not ok:
            self.counts["errors"] += 1

    def list_maps(self) -> tuple[dict[str, Any], dict[str, Any]]:
        maps = [
            {"name": m.name, "version": m.version, "gaussians": len(m.gmap),
             "has_mesh": m.has_mesh, "views": len(self._views(m))}
            for m in self.maps.values()
        ]  # fmt: skip
        return {"maps": maps}, {}

    def stats(self, now: float) -> tuple[dict[str, Any], dict[str, Any]]:
        job = self.job
        return {
            "uptime_s": now - self.started,
            "requests": self.counts["requests"],
            "errors": self.counts["errors"],
            "expired": self.counts["expired"],
            "repairs": self.counts["repairs"],
            "by_op": dict(self.by_op),
            "maps": {m.name: m.version for m in self.maps.values()},
            "busy": job is not None,
            "busy_s": now - job.started if job is not None else 0.0,
        }, {}

    def mesh_bytes(self, args: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        m = self.get(args.get("map"))
        fmt = _choice("fmt", args.get("fmt", "ply"), MESH_FORMATS)
        mesh = m.mesh()
        assert m.mesh_path is not None
        path = m.mesh_path
        if fmt == "ply" and path.suffix.lower() == ".ply":
            return {"format": fmt}, {"data": path.read_bytes()}

        def convert() -> bytes:
            from gsfix_online.mapping.mesh import write_mesh

            with tempfile.TemporaryDirectory() as tmp:
                return write_mesh(mesh, Path(tmp) / f"mesh.{fmt}").read_bytes()

        return {"format": fmt}, {"data": m.cached(f"mesh.{fmt}", m.mesh_version, convert)}

    def splat_bytes(self, args: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        m = self.get(args.get("map"))

        def encode() -> bytes:
            from gsfix_online.mapping.splat.ply import gaussians_to_ply

            if m.version == 0 and m.ply_path is not None:  # the file itself, bit for bit
                return m.ply_path.read_bytes()
            buf = io.BytesIO()
            gaussians_to_ply(m.gmap).write(buf)
            return buf.getvalue()

        return {"version": m.version}, {"data": m.cached("splats", m.version, encode)}

    def _views(self, m: ServedMap) -> list[dict[str, Any]]:
        def cam(kind: str, id: int, K: Any, T: Any, w: int, h: int, images: dict) -> dict:
            return {"kind": kind, "id": int(id), "K": np.asarray(K).ravel().tolist(),
                    "T_world_cam": np.asarray(T).ravel().tolist(), "width": int(w),
                    "height": int(h), "images": dict(images)}  # fmt: skip

        # a run's repaired views come as its views, below, not again among the map's cameras
        out = [cam("keyframe", k.id, k.K, k.T_world_cam, k.width, k.height, {})
               for k in m.keyframes if m.run is None or not k.repaired]  # fmt: skip
        if m.run is not None:
            out += [cam("view", v.view_id, v.K, v.T_world_cam, v.width, v.height, v.images)
                    for v in m.run.views]  # fmt: skip
        return out

    def views(self, args: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        return {"views": self._views(self.get(args.get("map")))}, {}

    def image(self, args: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        m = self.get(args.get("map"))
        rel = args.get("path")
        if m.run is None:
            raise RequestError("not_found", f"map {m.name!r} is live: it has no run folder")
        if not isinstance(rel, str) or not rel.lower().endswith(".png"):
            raise RequestError("bad_request", f"path must name a .png of the run, got {rel!r}")
        try:
            p = m.run.resolve(rel)
        except RunFolderError as exc:
            raise RequestError("bad_request", str(exc)) from None
        if not p.is_file():
            raise RequestError("not_found", f"map {m.name!r} has no image {rel}")
        return {"path": rel}, {"data": p.read_bytes()}

    def _view(self, args: dict[str, Any]) -> _View:
        w, h = _size(args)
        if w * h > self.cfg.max_pixels:
            raise RequestError("too_large", f"size too large: {w}x{h} = {w * h} pixels > "
                               f"max_pixels {self.cfg.max_pixels}")  # fmt: skip
        T = _numbers(args, "T_world_cam", 16).reshape(4, 4)
        K = _numbers(args, "K", 9).reshape(3, 3)
        try:
            T = check_pose(T)
        except FrameError as exc:
            raise RequestError("bad_request", f"bad pose: {exc}") from None
        try:
            intr = Intrinsics.from_K(K, w, h)
        except FrameError as exc:
            raise RequestError("bad_request", f"bad intrinsics: {exc}") from None
        return _View(T, intr)

    def render_gs(self, m: ServedMap, v: _View, shared: bool = True) -> tuple[Any, Any, Any]:
        """Colour [H, W, 3] uint8, depth and alpha; ``shared=False`` renders through a renderer
        of its own (a repair's worker), not the map's cached one."""
        if not shared:
            renderer = wrap_map(m.gmap, self.cfg.mapper)
        else:
            if m.renderer is None or m.renderer.gmap is not m.gmap:
                m.renderer = wrap_map(m.gmap, self.cfg.mapper)
            renderer = m.renderer
        k = v.intrinsics
        color, depth, alpha = renderer.render_numpy(v.T_world_cam, k.K, k.width, k.height)
        return _rgb8(color), depth.astype(np.float32), alpha.astype(np.float32)

    def synthesised(self, m: ServedMap, v: _View) -> npt.NDArray[np.float32]:  # [H, W] 0..1
        """Per pixel, the share of the 3DGS render's colour that Gaussians grown from repaired
        views make (0: all observed; mapping.splat.provenance.synthesised_share)."""
        from gsfix_online.mapping.splat.provenance import synthesised_share

        k = v.intrinsics
        share = synthesised_share(m.gmap, v.T_world_cam, k.K, k.width, k.height,
                                  self.cfg.mapper.backend)  # fmt: skip
        return np.asarray(share, np.float32)

    def render_provenance(self, m: ServedMap, v: _View) -> npt.NDArray[np.uint8]:  # [H, W]
        """:meth:`synthesised` times 255."""
        return np.rint(self.synthesised(m, v) * 255.0).astype(np.uint8)

    def render_mesh(self, m: ServedMap, v: _View) -> Any:
        if not m.has_mesh:
            raise RequestError("not_found", f"map {m.name!r} has no mesh to render")

        mesh = m.mesh()

        def build() -> Any:
            from gsfix_online.mapping.mesh_render import MeshRenderer

            return MeshRenderer(mesh)

        return m.cached("mesh_renderer", m.mesh_version, build).render(v.T_world_cam, v.intrinsics)

    def guess_depth(
        self, m: ServedMap, v: _View, valid: npt.NDArray[np.bool_]
    ) -> npt.NDArray[np.float32]:
        """The z-depth of the mesh's planes extended (mesh_planes) where the mesh render has no
        surface (``valid`` false), the planes fitted once per mesh."""
        from gsfix_online.mapping.mesh_planes import fit_planes, guessed_depth

        mesh = m.mesh()
        planes = m.cached("mesh_planes", m.mesh_version, lambda: fit_planes(mesh, self.cfg.guess))
        return guessed_depth(planes, v.T_world_cam, v.intrinsics, valid)

    def render(self, args: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        m = self.get(args.get("map"))
        source = _choice("source", args.get("source", "gs"), SOURCES)
        v = self._view(args)
        out: dict[str, Any] = {}
        if source in ("gs", "both"):
            out["color"], out["depth_m"], out["alpha"] = self.render_gs(m, v)
            out["provenance"] = self.render_provenance(m, v)
        if source in ("mesh", "both"):
            r = self.render_mesh(m, v)
            out["mesh"], out["depth_m"] = r.rgb(), r.depth_m
        return {"version": m.version, "source": source}, out

    # -- repair ------------------------------------------------------------------------------

    def begin_repair(self, args: dict[str, Any], now: float) -> RepairJob:
        """Check a repair request and take the one repair slot; the job then renders and
        repairs on a worker (:meth:`RepairJob.run`). Does no rendering itself."""
        if self.job is not None:
            raise RequestError("busy", f"busy: a repair of map {self.job.map.name!r} is running "
                               f"({now - self.job.started:.1f} s so far); ask again when it ends")  # fmt: skip
        m = self.get(args.get("map"))
        if m.run is None:
            raise RequestError("failed", f"map {m.name!r} is live: repairs go through its "
                               "planner's view_requests, not the map server")  # fmt: skip
        v = self._view(args)
        if not m.has_mesh:  # refused here, not on the worker after the slot was taken
            raise RequestError("not_found", f"map {m.name!r} has no mesh to render")
        self.job = RepairJob(m, v, self, now)
        return self.job

    def finish_repair(self, job: RepairJob, ok: bool) -> dict[str, Any]:
        """Swap the distilled copy in (a new version); returns the result for the client."""
        assert job is self.job
        self.job = None
        if not ok:
            return {}
        self.counts["repairs"] += 1
        m = job.map
        version = None
        if job.new_gmap is not None:
            m.gmap = job.new_gmap
            m.version += 1
            version = m.version
        return {**job.result, "map_version": version}

    def repairer_for(self, m: ServedMap, progress: Progress) -> Any:
        """The GSFixer of a map: its run's newest checkpoint, else ``fixer.model``."""
        from gsfix_online.repair.repairer import ViewRepairer

        if m.name not in self._repairers:
            rep = ViewRepairer(self.cfg.fixer)
            ckpt = (
                m.run.checkpoint_dir if m.run is not None and self.cfg.use_run_checkpoint else None
            )
            if ckpt is not None:
                progress(0.1, f"loading GSFixer from {ckpt}")
                rep.load_checkpoint(str(ckpt), version=1)
            else:
                progress(0.1, "loading the GSFixer base model")
                rep.load_base()
            self._repairers[m.name] = rep
        return self._repairers[m.name]

    def references_for(self, m: ServedMap, progress: Progress) -> Any:
        """The map's reference frames (a ReferenceStore; RunFolder.references), read on its
        first repair; None for a live map."""
        if m.run is None:
            return None
        if m.name not in self._references:
            n = len(m.run.reference_frames())
            progress(0.5, f"reading {n} reference frames of map {m.name!r}")
            self._references[m.name] = m.run.references(self.cfg.reference_capacity)
        return self._references[m.name]

    def choices_for(self, m: ServedMap) -> tuple[Any, float | None, Any]:
        """The held-out frames' choice, its reach and the trainer's choice the map's run
        repaired by (``RunFolder.choices``; repair.fallback.for_view takes them); GSFixer
        everywhere for a map whose run recorded none, or a live map."""
        from gsfix_online.repair.fallback import Choice, fixer_only

        if m.name not in self._choices:
            near, reach, trainer = m.run.choices() if m.run is not None else (None, None, None)
            self._choices[m.name] = (
                None if near is None else Choice.from_json(json.dumps(near)),
                reach,
                Choice.from_json(json.dumps(trainer)) if trainer
                else fixer_only("the run recorded no fallback choice"),
            )  # fmt: skip
        return self._choices[m.name]

    def keyframe_distance(
        self,
        m: ServedMap,
        v: _View,
        mesh_depth: npt.NDArray[np.float32],  # [H, W] m
        valid: npt.NDArray[np.bool_],  # [H, W]
    ) -> float | None:
        """The view's distance from the map's nearest input keyframe, as the planner measures
        it (repair.planner.keyframe_distance; repaired views are not keyframes here); None
        when the map names no input keyframe. A run's keyframes are every one its planner got:
        ``map/cameras.json`` holds only those the splat node's store kept to the end, and the
        trainer's ``work/keyframes`` every one that came (RunFolder.keyframe_poses)."""
        from gsfix_online.repair.planner import keyframe_distance

        poses = [k.T_world_cam for k in m.keyframes if not k.repaired]
        if m.run is not None:
            if m.name not in self._keyframe_poses:
                self._keyframe_poses[m.name] = m.run.keyframe_poses()
            poses += self._keyframe_poses[m.name]
        if not poses:
            return None
        z = float(np.median(mesh_depth[valid])) if valid.any() else 1.0
        return keyframe_distance(v.T_world_cam, np.stack(poses), z)
