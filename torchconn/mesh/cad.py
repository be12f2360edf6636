"""CAD input with exact features: CAD models and tagged gmsh files to a :class:`TetMesh` with
its CAD surfaces, feature curves and corner points as tagged entities (:class:`CadTags`).

- :func:`load_cad`: ``.step/.stp/.brep/.geo/.iges/.igs`` tetrahedralized by gmsh (the optional
  extra ``torchconn[cad]``), with a target size or a HexMe parameter file (``meta=``).
- :func:`load_tagged_msh`: a gmsh ``.msh`` (2.2 or 4.1) whose triangles, lines and points carry
  physical groups (read by meshio; gmsh is not needed).
- :func:`load_hexme`: a HexMe model from its ``c``/``u`` parameter file
  (``hexme/meta/XNNc_name.yaml``).

The tags are kept on the mesh as ``mesh.cad`` (:class:`CadTags`, ``None`` on an untagged mesh).
Every CAD entity becomes a tag as the HexMe dataset makes its meshes (its README): one physical
group per entity of every dimension, with the entity's own tag, so triangles carry their CAD
surface, lines their CAD curve and points their CAD corner. Downstream,
:class:`~torchconn.frames.constraints.BoundaryConstraint` takes the feature curves from
``mesh.cad`` instead of guessing them from dihedral angles.

gmsh, meshio and PyYAML are imported inside the functions that use them, so ``import
torchconn`` works without them.
"""
from __future__ import annotations

import math
import re
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from .errors import MeshError, _checked_path, _few
from .tet import TetMesh

__all__ = ["CadTags", "CAD_SUFFIXES", "load_cad", "load_tagged_msh", "load_hexme", "cad_tags_from_elements"]

CAD_SUFFIXES = (".step", ".stp", ".brep", ".geo", ".iges", ".igs")
_EXTRA = "pip install 'torchconn[cad]' (the gmsh package from PyPI)"


@dataclass(frozen=True)
class CadTags:
    """The CAD entities of a tet mesh (all ``torch.long``, on the mesh's device).

    Attributes (``F`` mesh faces, ``B`` boundary faces, ``K`` feature edges, ``C`` corners):

    * ``face_surface (F,)``: CAD surface tag of each row of ``mesh.faces``, ``-1`` on faces of
      no CAD surface (the interior).
    * ``boundary_face_surface (B,)``: the same for the rows of ``mesh.boundary_faces``
      (``face_surface[mesh.boundary_face_index]``).
    * ``feature_edges (K, 2)``: mesh edges on CAD curves, rows ``i < j`` sorted
      lexicographically; ``feature_edge_index (K,)`` their rows of ``mesh.edges`` and
      ``feature_edge_curve (K,)`` their CAD curve tag.
    * ``corner_vertices (C,)`` sorted mesh vertices on CAD points, ``corner_point (C,)`` their
      CAD point tag.

    A tag is the gmsh physical-group tag (by :func:`load_cad`: the CAD entity's own tag).
    """

    face_surface: torch.Tensor
    boundary_face_surface: torch.Tensor
    feature_edges: torch.Tensor
    feature_edge_index: torch.Tensor
    feature_edge_curve: torch.Tensor
    corner_vertices: torch.Tensor
    corner_point: torch.Tensor

    def to(self, device=None) -> "CadTags":
        """Copy with every tensor on ``device``."""
        return CadTags(**{f.name: getattr(self, f.name).to(device=device) for f in fields(self)})

    @property
    def n_surfaces(self) -> int:
        """Number of distinct CAD surfaces on the faces."""
        s = self.face_surface
        return int(torch.unique(s[s >= 0]).numel())

    @property
    def n_curves(self) -> int:
        """Number of distinct CAD curves on the feature edges."""
        return int(torch.unique(self.feature_edge_curve).numel())


# ----------------------------------------------------------------------------- tags from elements
def cad_tags_from_elements(mesh: TetMesh, triangles=None, triangle_tags=None, lines=None, line_tags=None,
                           points=None, point_tags=None, *, source: str = "elements") -> CadTags:
    """:class:`CadTags` of ``mesh`` from tagged lower-dimensional elements (mesh vertex indices).

    Args:
        mesh: the :class:`TetMesh` the elements live on.
        triangles: ``(N, 3)`` integer vertex indices, each a face of ``mesh``;
            ``triangle_tags (N,)`` their CAD surface tags.
        lines: ``(K, 2)`` integer vertex indices, each an edge of ``mesh``; ``line_tags (K,)``.
        points: ``(C,)`` integer vertex indices; ``point_tags (C,)``.
        source: what the elements came from, for error messages (a file name).

    A face, edge or vertex listed twice keeps its first tag. ``None`` means no elements of
    that kind.

    Raises:
        MeshError: a triangle that is no face of the mesh or a line that is no edge (naming
            the element index and its vertices), or tags of the wrong length.
    """
    dev = mesh.device
    V = mesh.n_vertices

    def arr(a, k):
        if a is None:
            return np.zeros((0, k) if k else (0,), np.int64)
        a = a.detach().cpu().numpy() if torch.is_tensor(a) else np.asarray(a)
        return a.astype(np.int64).reshape((-1, k) if k else (-1,))

    tri, tri_t = arr(triangles, 3), arr(triangle_tags, 0)
    lin, lin_t = arr(lines, 2), arr(line_tags, 0)
    pts, pts_t = arr(points, 0), arr(point_tags, 0)
    for what, a, t in (("triangle", tri, tri_t), ("line", lin, lin_t), ("point", pts, pts_t)):
        if a.shape[0] != t.shape[0]:
            raise MeshError(f"{source}: {a.shape[0]} {what}s but {t.shape[0]} {what} tags")
        bad = np.nonzero(((a < 0) | (a >= V)).reshape(a.shape[0], -1).any(axis=1))[0] if a.size else a[:0]
        if bad.size:
            raise MeshError(f"{source}: {what}s with vertex indices outside [0, {V}): {what} indices {_few(bad)}")

    # faces: key (edge id of the two smallest vertices) * V + largest vertex is monotone in the
    # lexicographic order of mesh.faces, so searchsorted finds each triangle
    F = mesh.n_faces
    face_surface = np.full(F, -1, np.int64)
    if tri.shape[0]:
        s = np.sort(tri, axis=1)
        fkeys = _face_keys(mesh.faces.cpu().numpy(), mesh.edge_keys().cpu().numpy(), V)
        tkeys = _face_keys(s, mesh.edge_keys().cpu().numpy(), V)
        pos = np.searchsorted(fkeys, tkeys).clip(max=F - 1)
        bad = np.nonzero((tkeys < 0) | (fkeys[pos] != tkeys))[0]
        if bad.size:
            raise MeshError(f"{source}: {bad.size} tagged triangles are not faces of the tet mesh: triangle indices "
                            f"{_few(bad)}, e.g. {tri[bad[0]].tolist()}; the surface mesh must be that of the tets")
        first = np.unique(pos, return_index=True)[1]
        face_surface[pos[first]] = tri_t[first]

    # feature edges: deduplicated, in edge order
    ekeys = mesh.edge_keys().cpu().numpy()
    if lin.shape[0]:
        lo, hi = lin.min(axis=1), lin.max(axis=1)
        keys = lo * V + hi
        pos = np.searchsorted(ekeys, keys).clip(max=max(ekeys.size - 1, 0))
        bad = np.nonzero((lo == hi) | (ekeys[pos] != keys))[0]
        if bad.size:
            raise MeshError(f"{source}: {bad.size} tagged lines are not edges of the tet mesh: line indices "
                            f"{_few(bad)}, e.g. {lin[bad[0]].tolist()}")
        eid, first = np.unique(pos, return_index=True)
        curve = lin_t[first]
    else:
        eid, curve = np.zeros(0, np.int64), np.zeros(0, np.int64)
    cv, first = np.unique(pts, return_index=True)
    lt = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.long, device=dev)  # noqa: E731
    fs = lt(face_surface)
    return CadTags(
        face_surface=fs,
        boundary_face_surface=fs[mesh.boundary_face_index],
        feature_edges=mesh.edges[lt(eid)].clone(),
        feature_edge_index=lt(eid),
        feature_edge_curve=lt(curve),
        corner_vertices=lt(cv),
        corner_point=lt(pts_t[first]),
    )


def _face_keys(sorted_tris: np.ndarray, edge_keys: np.ndarray, V: int) -> np.ndarray:
    """``edge_id(a, b) * V + c`` for sorted triangles ``[a<b<c]``; ``-1`` where ``(a, b)`` is no edge."""
    k = sorted_tris[:, 0] * V + sorted_tris[:, 1]
    pos = np.searchsorted(edge_keys, k).clip(max=max(edge_keys.size - 1, 0))
    ok = edge_keys[pos] == k
    return np.where(ok, pos * V + sorted_tris[:, 2], -1)


# ----------------------------------------------------------------------------- tagged .msh
def load_tagged_msh(path, *, tags: str = "auto", **kwargs) -> TetMesh:
    """Read a gmsh ``.msh`` with tagged triangles, lines and points into a :class:`TetMesh`
    whose ``mesh.cad`` holds them (:class:`CadTags`).

    Args:
        path: ``.msh`` file (MSH 2.2 or 4.1, ascii or binary) with ``tetra`` cells.
        tags: ``"physical"`` (gmsh physical groups), ``"geometrical"`` (the elementary entity
            tags) or ``"auto"`` (physical groups when the file has them, else geometrical).
        **kwargs: passed to :class:`TetMesh` (``dtype``, ``device``, ``reorient``); vertices
            used by no tet (gmsh's geometry points) are dropped and the tags re-indexed.

    Raises:
        MeshError: no tetrahedra, no tags of the requested kind, or tagged elements that are
            not faces/edges of the tets.
    """
    import meshio

    path = Path(path)
    if path.suffix.lower() != ".msh":
        raise MeshError(f"load_tagged_msh reads gmsh .msh files, got {path}")
    if not path.exists():
        raise FileNotFoundError(f"no such .msh file: {path}")
    try:
        m = meshio.read(str(path))
    except Exception as err:  # noqa: BLE001 - meshio raises its own exception types
        raise MeshError(f"could not read {path} with meshio: {err}") from err
    if tags == "auto" and not {"gmsh:physical", "gmsh:geometrical"} & set(m.cell_data):
        raise MeshError(f"{path} has no gmsh tags (neither 'gmsh:physical' nor 'gmsh:geometrical' cell data); "
                        f"use torchconn.io.load_tet_mesh for an untagged mesh")
    kwargs.setdefault("unreferenced", "drop")
    return _mesh_from_meshio(m, tags, str(path), **kwargs)


def _mesh_from_meshio(m, tags: str | None, source: str, **kwargs) -> TetMesh:
    """:class:`TetMesh` of the ``tetra`` blocks of ``m``, with ``mesh.cad`` from its gmsh tags
    (``tags``: ``"auto"``, ``"physical"``, ``"geometrical"`` or ``None``)."""
    if tags not in ("auto", "physical", "geometrical", None):
        raise ValueError(f"tags must be 'auto', 'physical', 'geometrical' or None, got {tags!r}")
    key = None
    if tags == "auto":
        key = next((k for k in ("gmsh:physical", "gmsh:geometrical") if k in m.cell_data), None)
    elif tags is not None:
        key = f"gmsh:{tags}"
        if key not in m.cell_data:
            raise MeshError(f"{source} has no {key!r} cell data (tags={tags!r}); it holds {sorted(m.cell_data)}")
    blocks: dict[str, list] = {"tetra": [], "triangle": [], "line": [], "vertex": []}
    tag_lists = m.cell_data[key] if key else [None] * len(m.cells)
    for block, tag in zip(m.cells, tag_lists):
        if block.type in blocks:
            data = np.asarray(block.data, np.int64)
            tag = np.zeros(data.shape[0], np.int64) if tag is None else np.asarray(tag, np.int64).reshape(-1)
            blocks[block.type].append((data, tag))
    if not blocks["tetra"]:
        raise MeshError(f"{source} contains no tetrahedra (cell blocks: {[c.type for c in m.cells]})")

    def cat(kind, k):
        if not blocks[kind]:
            return np.zeros((0, k), np.int64), np.zeros(0, np.int64)
        return (np.concatenate([b.reshape(-1, k) for b, _ in blocks[kind]]),
                np.concatenate([t for _, t in blocks[kind]]))

    tets, _ = cat("tetra", 4)
    points = np.asarray(m.points, np.float64)
    mesh = TetMesh(points, tets, **kwargs)
    if key is None:
        return mesh
    remap = np.full(points.shape[0], -1, np.int64)
    kept = mesh.kept_vertices.cpu().numpy()
    remap[kept] = np.arange(kept.size)
    tri, tri_t = cat("triangle", 3)
    lin, lin_t = cat("line", 2)
    pts, pts_t = cat("vertex", 1)
    pts = pts.reshape(-1)
    on_tets = remap[pts] >= 0  # a CAD point used by no tet has no mesh vertex
    mesh.cad = cad_tags_from_elements(mesh, remap[tri], tri_t, remap[lin], lin_t, remap[pts[on_tets]],
                                      pts_t[on_tets], source=source)
    return mesh


# ----------------------------------------------------------------------------- CAD through gmsh
def _import_gmsh():
    try:
        import gmsh
    except ImportError as err:
        raise ImportError(f"CAD input needs the gmsh Python package: {_EXTRA}") from err
    return gmsh


def _read_meta(meta) -> dict:
    """The ``gmsh.option.setNumber`` entries of a HexMe parameter file, as ``{name: value}``."""
    import yaml

    meta = Path(meta)
    with open(meta, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh) or {}
    if "gmsh.model.mesh.setSize" in doc:
        raise ValueError(f"{meta}: a box-embedded ('b') parameter file (it has 'gmsh.model.mesh.setSize'); "
                         f"load_cad does not build the surrounding box; use the model's 'c' or 'u' file")
    unknown = sorted(set(doc) - {"gmsh.option.setNumber", "info"})
    if unknown:
        raise ValueError(f"{meta}: unknown keys {unknown}; load_cad reads 'gmsh.option.setNumber' (and 'info')")
    opts = {}
    for i, entry in enumerate(doc.get("gmsh.option.setNumber") or []):
        if not isinstance(entry, dict) or len(entry) != 1:
            raise ValueError(f"{meta}: gmsh.option.setNumber entry {i} must be one 'Name: number', got {entry!r}")
        (name, value), = entry.items()
        opts[str(name)] = float(value)
    return opts


def load_cad(path, size: float | None = None, *, size_factor: float = 0.05, meta=None, threads: int | None = 1,
             options: dict | None = None, **kwargs) -> TetMesh:
    """Tetrahedralize a CAD model with gmsh and keep its entities as tags (``mesh.cad``).

    Args:
        path: ``.step/.stp/.brep/.iges/.igs`` (imported with OpenCASCADE; a file of faces
            without a solid, as IGES stores a body, is sewn into solids) or ``.geo`` (gmsh
            script, merged; it may set its own mesh options, which ``meta``/``size`` override).
        size: uniform target edge length (``Mesh.MeshSizeMin = Mesh.MeshSizeMax = size``,
            overriding ``meta`` and the script). ``None``: the sizes of ``meta`` when it sets
            ``Mesh.CharacteristicLengthMax``/``Mesh.MeshSizeMax``, else ``size_factor`` times
            the bounding-box diagonal.
        size_factor: see ``size``.
        meta: a HexMe parameter file (``hexme/meta/XNN{c,u}_name.yaml``): its
            ``gmsh.option.setNumber`` entries are applied before meshing, as the dataset does.
        threads: ``General.NumThreads``, applied last; 1 (default) makes gmsh's output
            reproducible (with more threads HXT varies by a few tets); ``None`` keeps the
            value of ``meta``.
        options: further ``gmsh.option.setNumber`` entries (``{name: number}``), applied after
            ``meta``'s (e.g. ``{"Mesh.CharacteristicLengthMax": 0.15}`` for a finer mesh of a
            ``c`` parameter file).
        **kwargs: passed to :class:`TetMesh` (``dtype``, ``device``).

    Returns:
        a :class:`TetMesh` with ``mesh.cad`` (:class:`CadTags`): CAD surface per face, CAD
        curve per feature edge, CAD point per corner vertex.

    Physical groups defined by a ``.geo`` script are replaced by one group per CAD entity
    (use :func:`load_tagged_msh` on gmsh's own output to keep a script's groups).

    gmsh is initialized with ``General.Terminal = 0`` and finalized on every path (when this
    call initialized it; an already initialized gmsh session is left running, its current
    model untouched). A ``.geo`` script that calls ``Exit`` is refused, since gmsh would end
    the Python process.

    Raises:
        ImportError: gmsh missing (install ``torchconn[cad]``).
        MeshError: unsupported suffix, a model without volumes, or a gmsh failure (its message).
        ValueError: a bad ``size``/``meta``.
    """
    path, suf = _checked_path(path, CAD_SUFFIXES, "CAD")
    if size is not None and not (math.isfinite(size) and size > 0):
        raise ValueError(f"size must be a positive number, got {size}")
    if not size_factor > 0:
        raise ValueError(f"size_factor must be positive, got {size_factor}")
    if suf == ".geo" and re.search(r"(?m)^\s*Exit\s*;", path.read_text(encoding="utf-8", errors="replace")):
        raise MeshError(f"{path} calls 'Exit;', which would end the Python process inside gmsh; remove that line")
    opts = _read_meta(meta) if meta is not None else {}
    for k, v in (options or {}).items():
        if not isinstance(k, str) or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"options must map gmsh option names to finite numbers, got {k!r}: {v!r}")
        opts[k] = float(v)
    gmsh = _import_gmsh()
    own = not gmsh.isInitialized()
    if own:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    previous = None if own else gmsh.model.getCurrent()
    name = "torchconn_load_cad"
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(name)
        try:
            if suf == ".geo":
                gmsh.merge(str(path))
            else:
                gmsh.model.occ.importShapes(str(path))
                gmsh.model.occ.synchronize()
                if not gmsh.model.getEntities(3) and gmsh.model.getEntities(2):
                    # IGES (and some STEP files) hold trimmed faces, not solids: sew them
                    gmsh.model.occ.healShapes(sewFaces=True, makeSolids=True)
                    gmsh.model.occ.synchronize()
        except Exception as err:  # noqa: BLE001 - gmsh raises bare Exception
            raise MeshError(f"gmsh could not read {path}: {err}") from err
        if not gmsh.model.getEntities(3):
            raise MeshError(f"{path} has no volume (only {len(gmsh.model.getEntities(2))} surfaces); "
                            f"load_cad meshes solids")
        gmsh.model.removePhysicalGroups()  # the script's own groups would hide untagged entities
        for dim in range(4):  # one physical group per entity, with its own tag (HexMe's procedure)
            for d, tag in gmsh.model.getEntities(dim):
                gmsh.model.addPhysicalGroup(d, [tag], tag)
        for k, v in opts.items():
            gmsh.option.setNumber(k, v)
        if size is None and "Mesh.CharacteristicLengthMax" not in opts and "Mesh.MeshSizeMax" not in opts:
            lo = np.array(gmsh.model.getBoundingBox(-1, -1)[:3])
            hi = np.array(gmsh.model.getBoundingBox(-1, -1)[3:])
            size = size_factor * float(np.linalg.norm(hi - lo))
        if size is not None:
            # both bounds: the sizes gmsh attaches to CAD points would otherwise win
            gmsh.option.setNumber("Mesh.MeshSizeMax", float(size))
            gmsh.option.setNumber("Mesh.MeshSizeMin", float(size))
        if threads is not None:
            gmsh.option.setNumber("General.NumThreads", int(threads))
        try:
            gmsh.model.mesh.generate(3)
        except Exception as err:  # noqa: BLE001
            raise MeshError(f"gmsh could not mesh {path}: {err}") from err
        with tempfile.TemporaryDirectory(prefix="torchconn_cad_") as tmp:
            out = Path(tmp) / "mesh.msh"
            gmsh.write(str(out))
            return load_tagged_msh(out, tags="physical", **kwargs)
    finally:
        if own:
            gmsh.finalize()
        else:
            gmsh.model.setCurrent(name)
            gmsh.model.remove()
            if previous:
                gmsh.model.setCurrent(previous)


def load_hexme(meta, size: float | None = None, **kwargs) -> TetMesh:
    """A HexMe model meshed with its own parameter file ``hexme/meta/XNN{c,u}_name.yaml``.

    The parameter file names its model file (``info: meta/XNNo_name.yaml``, whose ``original:``
    is the CAD path), both relative to the dataset root (the parent of ``meta/``).
    ``size`` and ``kwargs`` go to :func:`load_cad`.
    """
    import yaml

    meta = Path(meta)
    root = meta.resolve().parent.parent
    with open(meta, encoding="utf-8") as fh:
        info = (yaml.safe_load(fh) or {}).get("info")
    if not info:
        raise ValueError(f"{meta} has no 'info:' entry naming the model's XNNo_name.yaml")
    with open(root / info, encoding="utf-8") as fh:
        original = (yaml.safe_load(fh) or {}).get("original")
    if not original:
        raise ValueError(f"{root / info} has no 'original:' entry naming the CAD file")
    return load_cad(root / original, size, meta=meta, **kwargs)
