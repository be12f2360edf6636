"""Tests of the shared mesh layer: MeshBase (edge lookup, face loops, buffers, to(), require),
the one home of the simplex templates, and the layering of torchconn/mesh."""
import ast
from pathlib import Path

import numpy as np
import pytest
import torch

import torchconn
from torchconn.dec import dnabla, transport
from torchconn.dec.connection import Connection
from torchconn.mesh import CellComplex, FaceGroup, MeshBase, MeshError, TetMesh, box, simplex
from torchconn.mesh.base import lookup_edges
from torchconn.mesh.cells import face_groups_from_buffers
from torchconn.nn import MeshBuffers

MESH_DIR = Path(torchconn.__file__).parent / "mesh"


@pytest.fixture(scope="module")
def tet():
    return box(n=2)


@pytest.fixture(scope="module")
def cells():
    # a quad and a pentagon sharing edge 1-2, plus a triangle: three face sizes
    V = torch.rand(7, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return CellComplex(V, [[0, 1, 2, 3], [2, 1, 4, 5, 6], [0, 3, 6]])


def _slow_edge_ids(edges: torch.Tensor, i, j):
    """Reference: a Python dict from canonical pair to row."""
    table = {(int(a), int(b)): e for e, (a, b) in enumerate(edges.tolist())}
    return [table[(min(a, b), max(a, b))] for a, b in zip(i, j)], [1 if a < b else -1 for a, b in zip(i, j)]


# ----------------------------------------------------------------------------- shared base
def test_both_kinds_share_the_base(tet, cells):
    assert isinstance(tet, MeshBase) and isinstance(cells, MeshBase)
    assert TetMesh.edge_index is CellComplex.edge_index is MeshBase.edge_index
    assert TetMesh.to is CellComplex.to is MeshBase.to
    assert (tet.kind, cells.kind) == ("tet", "cells")
    for m in (tet, cells):
        e = m.edges
        assert (e[:, 0] < e[:, 1]).all()
        keys = m.edge_keys()
        assert (keys[1:] > keys[:-1]).all()  # sorted rows, hence sorted keys


@pytest.mark.parametrize("which", ["tet", "cells"])
def test_edge_index_against_slow_reference(which, tet, cells):
    m = tet if which == "tet" else cells
    e = m.edges
    i = torch.cat([e[:, 0], e[:, 1]])
    j = torch.cat([e[:, 1], e[:, 0]])
    idx, sign = m.edge_index(i, j)
    ref_idx, ref_sign = _slow_edge_ids(e, i.tolist(), j.tolist())
    assert idx.tolist() == ref_idx and sign.tolist() == ref_sign
    assert idx.dtype == sign.dtype == torch.long
    # broadcasting and shapes (...)
    idx2, sign2 = m.edge_index(e[:4, 0].reshape(2, 2), e[:4, 1].reshape(2, 2))
    assert idx2.shape == (2, 2) and torch.equal(idx2.reshape(-1), torch.arange(4)) and (sign2 == 1).all()


@pytest.mark.parametrize("which", ["tet", "cells"])
def test_edge_index_error_names_missing_pairs(which, tet, cells):
    m = tet if which == "tet" else cells
    a, b = int(m.edges[0, 0]), int(m.edges[0, 1])
    present = {tuple(r) for r in m.edges.tolist()}
    missing = next((p, q) for p in range(m.n_vertices) for q in range(p + 1, m.n_vertices) if (p, q) not in present)
    name = type(m).__name__
    with pytest.raises(MeshError, match=rf"2 vertex pairs are not edges of the {name}: \[\[{missing[1]}, {missing[0]}\], \[3, 3\]\]"):
        m.edge_index(torch.tensor([a, missing[1], 3]), torch.tensor([b, missing[0], 3]))
    with pytest.raises(MeshError, match=rf"not edges of the {name}: \[\[-1, {a}\]\]"):
        m.edge_index(torch.tensor([-1]), torch.tensor([a]))
    with pytest.raises(TypeError, match="integer"):
        m.edge_index(torch.tensor([0.0]), torch.tensor([1.0]))


def test_connection_uses_the_same_lookup_and_raises_mesh_error(tet):
    perm = torch.randperm(tet.n_edges, generator=torch.Generator().manual_seed(1))
    edges = tet.edges[perm]  # canonical rows in another order
    conn = Connection.random(edges, tet.n_vertices, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    i, j = tet.edges[:, 1], tet.edges[:, 0]
    idx, sign = conn.edge_index(i, j)
    ref_idx, ref_sign = _slow_edge_ids(edges, i.tolist(), j.tolist())
    assert idx.tolist() == ref_idx and sign.tolist() == ref_sign
    with pytest.raises(MeshError, match=r"1 vertex pairs are not edges of the connection: \[\[4, 4\]\]"):
        conn.edge_index(torch.tensor([4]), torch.tensor([4]))
    assert issubclass(MeshError, ValueError)


def test_lookup_edges_on_empty_keys():
    with pytest.raises(MeshError, match=r"not edges of the mesh: \[\[0, 1\]\]"):
        lookup_edges(torch.zeros(0, dtype=torch.long), 3, torch.tensor([0]), torch.tensor([1]))


# ----------------------------------------------------------------------------- face loops
@pytest.mark.parametrize("which", ["tet", "cells"])
def test_face_loops_walk_their_edges(which, tet, cells):
    m = tet if which == "tet" else cells
    groups = m.face_loops()
    ids = torch.cat([g.face_ids for g in groups.values()])
    assert torch.equal(ids.sort().values, torch.arange(m.n_faces))
    for size, g in groups.items():
        assert isinstance(g, FaceGroup) and g.loops.shape[1] == size
        start, end = g.loops, g.loops.roll(-1, dims=1)
        stored = m.edges[g.loop_edges]  # (F_m, m, 2)
        fwd = torch.where((g.loop_signs > 0)[..., None], stored, stored.flip(-1))
        assert torch.equal(fwd[..., 0], start) and torch.equal(fwd[..., 1], end)


def test_tet_face_loops_match_the_cell_complex_view(tet):
    mine = tet.face_loops()[3]
    theirs = tet.as_cell_complex().face_groups[3]
    for f in FaceGroup.FIELDS:
        assert torch.equal(getattr(mine, f), getattr(theirs, f))
    assert tet.face_loops() is tet.face_loops()  # cached by require()
    assert not hasattr(tet, "face_groups")  # ops.fast tells a tet mesh by its absence


# ----------------------------------------------------------------------------- require / to / buffers
@pytest.mark.parametrize("which", ["tet", "cells"])
def test_require_caches_once_and_to_gives_a_fresh_cache(which, tet, cells):
    m = (tet if which == "tet" else cells).to()  # a private copy: the module fixture stays clean
    calls = []

    def builder(mesh):
        calls.append(mesh)
        return mesh.edges[:, 0] + mesh.edges[:, 1]

    a = m.require("edge_sum", builder)
    assert m.require("edge_sum", builder) is a and calls == [m]
    m32 = m.to(dtype=torch.float32)
    b = m32.require("edge_sum", builder)
    assert b is not a and calls == [m, m32] and torch.equal(a, b)
    assert m.require("edge_sum", builder) is a  # the original keeps its cache


@pytest.mark.parametrize("which", ["tet", "cells"])
def test_to_moves_every_buffer(which, tet, cells):
    m = tet if which == "tet" else cells
    m32 = m.to(dtype=torch.float32)
    assert type(m32) is type(m) and m32.dtype == torch.float32
    before, after = m.buffers(), m32.buffers()
    assert before.keys() == after.keys()
    for name, t in before.items():
        u = after[name]
        if t.is_floating_point():
            assert u.dtype == torch.float32
            torch.testing.assert_close(u, t.float(), rtol=0, atol=0)
        else:
            assert u.dtype == t.dtype and torch.equal(u, t)
    with pytest.raises(TypeError, match="floating"):
        m.to(dtype=torch.int64)


def test_buffers_cover_the_declared_names(tet, cells):
    assert set(tet.buffers()) == set(TetMesh._INT_BUFFERS + TetMesh._FLOAT_BUFFERS)
    groups = face_groups_from_buffers(cells.buffers())
    assert sorted(groups) == sorted(cells.face_groups) == [3, 4, 5]
    for m, g in groups.items():
        for f in FaceGroup.FIELDS:
            assert getattr(g, f) is getattr(cells.face_groups[m], f)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("which", ["tet", "cells"])
def test_to_cuda_and_lookup_there(which, tet, cells):
    m = (tet if which == "tet" else cells).to("cuda")
    assert all(t.device.type == "cuda" for t in m.buffers().values())
    idx, sign = m.edge_index(m.edges[:, 1], m.edges[:, 0])
    assert idx.device.type == "cuda" and torch.equal(idx.cpu(), torch.arange(m.n_edges)) and (sign == -1).all()
    for g in m.face_loops().values():
        assert g.loops.device.type == "cuda"


def test_mesh_buffers_register_the_mesh_buffers(tet, cells):
    for m in (tet, cells):
        mb = MeshBuffers(m)
        names = dict(mb.named_buffers())
        assert names.keys() == m.buffers().keys() and mb.kind == m.kind
        for k, t in m.buffers().items():
            assert torch.equal(names[k], t)
            assert t.numel() == 0 or names[k].data_ptr() != t.data_ptr()  # a copy, not the mesh's tensor
    groups = MeshBuffers(cells).face_groups
    assert sorted(groups) == [3, 4, 5] and torch.equal(groups[5].loops, cells.face_groups[5].loops)
    with pytest.raises(AttributeError, match="face_groups"):
        MeshBuffers(tet).face_groups
    with pytest.raises(TypeError, match="TetMesh or a CellComplex"):
        MeshBuffers(object())


# ----------------------------------------------------------------------------- one home, layering
def test_simplex_templates_have_one_home():
    assert transport.pair_list is simplex.pair_list
    assert dnabla.TET_FACES is simplex.TET_FACES
    assert dnabla.TET_FACE_SIGNS is simplex.TET_FACE_SIGNS
    assert dnabla.FACE_EDGE_SIGNS is simplex.FACE_EDGE_SIGNS
    assert simplex.pair_list(4) == ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    # boundary of the boundary vanishes: each tet edge gets opposite coefficients from its two faces
    coef = {}
    for k, face in enumerate(simplex.TET_FACES):
        for m in range(3):
            edge = tuple(v for s, v in enumerate(face) if s != m)
            coef[edge] = coef.get(edge, 0) + simplex.TET_FACE_SIGNS[k] * simplex.FACE_EDGE_SIGNS[m]
    assert sorted(coef) == list(simplex.pair_list(4)) and set(coef.values()) == {0}


def _imported_modules(path: Path) -> list[str]:
    """Absolute names of the torchconn modules imported by ``path`` (a module of torchconn.mesh)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                out.append(node.module or "")
            else:
                base = ["torchconn", "mesh"][: 3 - node.level]
                out.append(".".join(base + ([node.module] if node.module else [])))
    return out


def test_mesh_layer_imports_nothing_above_it():
    files = sorted(MESH_DIR.glob("*.py"))
    assert {p.stem for p in files} >= {"base", "tet", "cells", "simplex", "errors", "io", "builtin"}
    above = ("torchconn.dec", "torchconn.nn", "torchconn.frames")
    for p in files:
        bad = [m for m in _imported_modules(p) if m.startswith(above)]
        assert not bad, f"{p.name} imports {bad}"
        assert len(p.read_text().splitlines()) < 600, f"{p.name} is over 600 lines"


def test_mesh_io_libraries_are_imported_lazily():
    libs = {"meshio", "igl", "pymeshlab"}
    for p in sorted(MESH_DIR.glob("*.py")):
        tree = ast.parse(p.read_text())
        for node in tree.body:  # module level only
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n.split(".")[0] in libs for n in names), f"{p.name} imports {names} at module level"


def test_public_mesh_names_keep_working():
    io = torchconn.mesh.io
    for name in ("box", "ball", "cylinder", "torus", "tetrahedralize", "load_mesh", "load_tet_mesh",
                 "load_surface", "load_polygon_surface"):
        assert getattr(io, name) is getattr(torchconn.mesh, name)
    assert torchconn.io is io
    assert np.array_equal(torchconn.io.box(n=1).tets.numpy(), box(n=1).tets.numpy())
