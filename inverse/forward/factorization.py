"""Photometric factorization A(θ) y = b (docs/method.md §2, dissertation eq. 2.5–2.8).

Every tree node contributes ``fresnel · Π(path factors) · Σ_j a_j(θ) x_j`` to its pixel, where
``a_j(θ) = Σ_k V_k I_k / d_k² · g_j(θ; n, l_k, v)`` (per band through ``I_k``). Grouping the nodes
by *monomial* — the surface of the node and the multiset of the ``r_s`` / ``t_s`` factors on its
path (order does not matter) — gives one column per (monomial, linear parameter ``x_j``): column
entry = Σ over that pixel's nodes of that monomial of ``fresnel · a_j(θ)``, and

    B_pixel,c = Σ_col A_c[pixel, col](θ) · y_c[col],    y_c[col] = x_j,c · Π r_s,c^e · t_s,c^e.

Only the monomials that occur in the scene are kept; the dissertation's dense ``y`` has
``len(x̃) · (1 + 2N)^(D−1)`` entries (:attr:`Factorization.dense_columns`).

The sparsity pattern (which pixel meets which column) is fixed by the trees; only the values
depend on θ, so each evaluation is a weighted ``bincount`` into a stored CSR pattern.

Nonlinear parameters are handled in the model's natural units here; :mod:`reflab.inverse.fit.rounds`
maps them to its search space (log2 shininess).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

BANDS = 3


def one_blas_thread(func):
    """Run ``func`` with BLAS (OpenBLAS in numpy and scipy) on one thread.

    The fit's dense products are small (monomial space, or R × a few dozen columns): OpenBLAS's
    threads cost more than they gain, and on a loaded machine their spin-waiting halves the speed.
    Measured on the 320×240 demo, 2 cores at load ≈ 4.5: one fit 25.4 s → 13.8 s, and the inner
    gradient 6.7 → 1.2 ms, the normal matrix 92 → 26 ms (docs/fit.md, "Speed").
    """
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper


@dataclass
class Layout:
    """Where each surface's parameters live in the flat parameter vectors.

    Attributes
    ----------
    x_offset : (S + 1,) int
        Linear parameters of surface ``s`` are ``x[x_offset[s]:x_offset[s+1]]`` (rows of an (X, 3) array).
    x_names : list of (surface, name)
        Name of each flat linear parameter.
    theta_offset : (S + 1,) int
        Nonlinear parameters of surface ``s`` are ``theta[theta_offset[s]:theta_offset[s+1]]`` (shared by bands).
    theta_names : list of (surface, name)
        Name of each flat nonlinear parameter.
    n_factors : int
        ``2 S``: factor ``2 s`` is ``r_s``, factor ``2 s + 1`` is ``t_s`` (rows of an (F, 3) array).
    """

    x_offset: np.ndarray
    x_names: list
    theta_offset: np.ndarray
    theta_names: list
    n_factors: int

    @property
    def n_x(self) -> int:
        return int(self.x_offset[-1])

    @property
    def n_theta(self) -> int:
        return int(self.theta_offset[-1])


class Matrices(list):
    """The system's A_c per band (CSR), with each band's dense Gram matrix A_cᵀA_c computed once,
    when first asked for: the inner solve, the θ curvature and the σ of one θ all use it."""

    def gram(self, c: int) -> np.ndarray:
        grams = self.__dict__.setdefault("_grams", {})
        if c not in grams:
            grams[c] = (self[c].T @ self[c]).toarray()
        return grams[c]


def _light_sum(w, g) -> np.ndarray:
    """Σ_k w[:, k, :] · g[:, k] (n, 3): one column's value per node and band, summed over the K lights."""
    out = w[:, 0] * g[:, 0, None]
    for k in range(1, w.shape[1]):
        out += w[:, k] * g[:, k, None]
    return out


def gram(A, c: int) -> np.ndarray:
    """A_cᵀA_c (dense) of a :class:`Matrices` (kept) or of any list of sparse matrices."""
    return A.gram(c) if isinstance(A, Matrices) else (A[c].T @ A[c]).toarray()


def canonical_paths(paths) -> tuple[np.ndarray, list]:
    """Map ordered paths to their multiset of factors.

    Parameters
    ----------
    paths : list of tuples of (surface, kind)
        ``trees.paths``.

    Returns
    -------
    canon : (len(paths),) int
        Index of each path's sorted factor tuple in ``unique``.
    unique : list of tuples of int
        Sorted factor indices ``2 s + kind`` of each distinct multiset.
    """
    index, unique, canon = {}, [], np.empty(len(paths), dtype=np.int64)
    for i, path in enumerate(paths):  # one entry per distinct path, not per pixel
        key = tuple(sorted(2 * int(s) + int(k) for s, k in path))
        if key not in index:
            index[key] = len(unique)
            unique.append(key)
        canon[i] = index[key]
    return canon, unique


class Factorization:
    """The factorized system of one scene: fixed sparsity, θ-dependent values.

    Parameters
    ----------
    trees : Trees
        Pixel-intensity trees (docs/architecture.md): ``pixel, surface, normal, view, fresnel,
        path, paths, light_dir, light_dist2, visible, width, height, depth``.
    models : list
        One model per surface (``reflab.inverse.forward.models.get_model(brdf)``): ``.linear`` and
        ``.nonlinear`` name tuples, ``g(theta, n, l, v) -> (N, L)``, ``dg(...) -> (N, L, P)``.
    intensities : (K, 3) array_like
        Radiant intensity of each light per band.
    mask : (H*W,) bool, optional
        Pixels to use (False drops e.g. saturated pixels). Rows of every matrix are the used
        pixels, in :attr:`rows` order.
    albedo : (N, 3) array_like, optional
        A known diffuse texture: per tree node and band, a factor on the ``kd`` term of the
        node's surface (NaN or absent: 1). The surface's ``kd`` parameter is then a gain on that
        texture (1 where the texture is right), and the fit judges the other parameters against
        it instead of against a homogeneous albedo.
    weights : (H*W,) array_like, optional
        Per pixel, the weight of its row in the least squares (a sample's 1/inclusion probability,
        :mod:`reflab.inverse.fit.sampling`): its row of every ``A_c`` (and of ∂A/∂θ) is scaled by
        ``sqrt(weight)``, as :class:`reflab.inverse.fit.problem.Problem` scales ``b``. Default: the
        trees' ``weights`` attribute when they carry one (a sample's trees, so that every system
        built on them weighs alike), else none (every row weight 1).

    Attributes
    ----------
    rows : (R,) int
        Pixel index of each matrix row.
    row_scale : (R,) ndarray or None
        ``sqrt(weight)`` of each row (None: unweighted).
    layout : Layout
    col_x : (C,) int
        Flat linear parameter of each column.
    exponents : (C, F) int
        Degree of each factor in each column's monomial.
    monomials : list of (surface, factor tuple)
        The monomial of each distinct column group.
    """

    def __init__(self, trees, models, intensities, mask=None, albedo=None, weights=None):
        self.trees = trees
        self.models = list(models)
        if weights is None:
            weights = getattr(trees, "weights", None)
        self._args = (intensities, mask, albedo, weights)  # for :meth:`without`
        n_surf = len(self.models)
        self.width, self.height, self.depth = int(trees.width), int(trees.height), int(trees.depth)
        n_pix = self.width * self.height
        mask = np.ones(n_pix, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(n_pix)
        self.rows = np.flatnonzero(mask)
        row_of_pixel = np.full(n_pix, -1, dtype=np.int64)
        row_of_pixel[self.rows] = np.arange(len(self.rows))

        n_lin = np.array([len(m.linear) for m in self.models], dtype=np.int64)
        n_non = np.array([len(m.nonlinear) for m in self.models], dtype=np.int64)
        x_off = np.concatenate([[0], np.cumsum(n_lin)])
        t_off = np.concatenate([[0], np.cumsum(n_non)])
        self.layout = Layout(
            x_off, [(s, p) for s, m in enumerate(self.models) for p in m.linear],
            t_off, [(s, p) for s, m in enumerate(self.models) for p in m.nonlinear], 2 * n_surf)

        pixel = np.asarray(trees.pixel, dtype=np.int64)
        surface = np.asarray(trees.surface, dtype=np.int64)
        if len(pixel) and (surface.min() < 0 or surface.max() >= n_surf):
            raise ValueError(f"trees reference surface {surface.max()} but the scene has {n_surf} surfaces")
        intensities = np.asarray(intensities, dtype=np.float64).reshape(-1, BANDS)
        # Known, θ-independent per-node-per-light weights: fresnel · V_k · I_k / d_k².
        weight = (np.asarray(trees.fresnel, dtype=np.float64)[:, None, None]
                  * np.asarray(trees.visible, dtype=np.float64)[:, :, None]
                  * intensities[None, :, :] / np.asarray(trees.light_dist2, dtype=np.float64)[:, :, None])
        keep = (row_of_pixel[pixel] >= 0) & np.any(weight > 0, axis=(1, 2))
        self.node = np.flatnonzero(keep)
        self.weight = weight[self.node]
        self.row_scale = None
        if weights is not None:
            # A row weighed w is the row scaled by sqrt(w): every entry and θ-derivative is linear
            # in these per-node weights, so scaling them scales the whole row.
            self.row_scale = np.sqrt(np.asarray(weights, dtype=np.float64).reshape(n_pix)[self.rows])
            self.weight = self.weight * self.row_scale[row_of_pixel[pixel[self.node]]][:, None, None]
        self.albedo = None
        if albedo is not None:
            albedo = np.asarray(albedo, dtype=np.float64).reshape(len(pixel), BANDS)[self.node]
            self.albedo = np.where(np.isfinite(albedo), albedo, 1.0)
        node_surf = surface[self.node]

        # Monomial of each node: (surface, multiset of path factors).
        canon, unique = canonical_paths(trees.paths)
        key = node_surf * max(len(unique), 1) + canon[np.asarray(trees.path, dtype=np.int64)[self.node]]
        mono_key, node_mono = np.unique(key, return_inverse=True)
        mono_surf = mono_key // max(len(unique), 1)
        mono_path = mono_key % max(len(unique), 1)
        self.monomials = [(int(s), unique[p]) for s, p in zip(mono_surf, mono_path)]
        mono_exp = np.zeros((len(mono_key), 2 * n_surf), dtype=np.int64)
        for m, (_, factors) in enumerate(self.monomials):  # one row per distinct monomial
            np.add.at(mono_exp[m], list(factors), 1)

        # Columns: (monomial, linear parameter j of the monomial's surface).
        mono_ncol = n_lin[mono_surf]
        mono_col0 = np.concatenate([[0], np.cumsum(mono_ncol)])
        n_col = int(mono_col0[-1])
        col_mono = np.repeat(np.arange(len(mono_key)), mono_ncol)
        col_j = np.arange(n_col) - mono_col0[col_mono]
        self.col_x = x_off[mono_surf[col_mono]] + col_j
        self.exponents = mono_exp[col_mono]
        self._used = np.flatnonzero(self.exponents.any(axis=0))  # factors that occur at all
        # Each column's factors as indices into the used factors, repeated by degree and padded
        # with the index of a row of ones: a product is a few gathers (factor_products).
        exp_used = self.exponents[:, self._used]
        degree = int(exp_used.sum(axis=1).max()) if exp_used.size else 0
        self._factor_index = np.full((n_col, max(degree, 1)), len(self._used), dtype=np.int64)
        for c in np.flatnonzero(exp_used.any(axis=1)):  # one row per column
            idx = np.repeat(np.arange(len(self._used)), exp_used[c])
            self._factor_index[c, :len(idx)] = idx
        self.col_surface = mono_surf[col_mono]

        # Entries: one per (kept node, linear parameter of its surface), grouped by surface so
        # that each model is evaluated once per light on all its nodes.
        order = np.argsort(node_surf, kind="stable")
        self._groups = []
        entry_node, entry_col, entry_theta = [], [], []
        start = 0
        for s in range(n_surf):  # one vectorised block per surface
            idx = order[np.searchsorted(node_surf[order], s):np.searchsorted(node_surf[order], s, side="right")]
            if len(idx) == 0:
                continue
            J = int(n_lin[s])
            self._groups.append((s, idx, start, J))
            entry_node.append(np.repeat(idx, J))
            entry_col.append((mono_col0[node_mono[idx]][:, None] + np.arange(J)[None, :]).ravel())
            start += len(idx) * J
        entry_node = np.concatenate(entry_node) if entry_node else np.zeros(0, np.int64)
        entry_col = np.concatenate(entry_col) if entry_col else np.zeros(0, np.int64)
        self.entry_col = entry_col
        self.entry_row = row_of_pixel[pixel[self.node[entry_node]]]

        # Fixed CSR pattern: entries of one (row, column) pair sum into one slot.
        slot_key, self.entry_slot = np.unique(self.entry_row * max(n_col, 1) + entry_col, return_inverse=True)
        self.n_rows, self.n_columns = len(self.rows), n_col
        self._indices = (slot_key % max(n_col, 1)).astype(np.int32)
        self._indptr = np.searchsorted(slot_key // max(n_col, 1), np.arange(self.n_rows + 1)).astype(np.int64)
        self._n_slots = len(slot_key)
        self._slot_order = None  # entries in CSR order (False: some share a slot), set by _assemble
        self._values = None  # (E, 3) entry values of the last evaluation (:meth:`_entries`)
        self._last = {}  # surface -> (θ of its values, their θ-derivatives or None)
        self._geometry = {}  # surface -> its model's θ-independent terms per (node, light)
        self._theta_rows_cache = {}  # θ indices -> (rows they act on, each entry's index among them)

    def without(self, pixels) -> "Factorization":
        """The same system with the flat pixel indices ``pixels`` left out too (rejected outliers)."""
        intensities, mask, albedo, weights = self._args
        n_pix = self.width * self.height
        keep = np.ones(n_pix, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(n_pix).copy()
        keep[np.asarray(pixels, dtype=np.int64)] = False
        return Factorization(self.trees, self.models, intensities, mask=keep, albedo=albedo, weights=weights)

    # ------------------------------------------------------------------ sizes
    @property
    def dense_columns(self) -> int:
        """Column count of the dissertation's dense ``y = x̃ ⊗ Kron^{D−1}(1 ⇓ r̃ ⇓ t̃)``: O(N^D)."""
        return int(self.layout.n_x * (1 + self.layout.n_factors) ** max(self.depth - 1, 0))

    def column_names(self) -> list[str]:
        """Readable monomial of each column, e.g. ``kd[floor]·r[mirror]·t[sheet]²`` with surface indices."""
        out = []
        for c in range(self.n_columns):
            s, name = self.layout.x_names[self.col_x[c]]
            text = f"{name}{s}"
            for f in np.flatnonzero(self.exponents[c]):
                text += f"·{'rt'[f % 2]}{f // 2}" + (f"^{self.exponents[c, f]}" if self.exponents[c, f] > 1 else "")
            out.append(text)
        return out

    # ------------------------------------------------------------------ values
    def _entries(self, theta, grad: bool):
        """Entry values (E, 3) and, with ``grad``, a list of (entries, dvalues (P, 3, len(entries)), θ offset):
        per surface with θ, the entries of its θ-shaped columns (the others' derivatives are 0).

        The values are kept between calls in one array (valid until the next call): a surface's
        block is recomputed only when its θ changed (a scan over one surface's θ recomputes only
        that surface; surfaces without θ never), and then only its columns that θ shapes
        (``Model.shaped``: a Phong kd's n·l does not move with ns); each model's θ-independent
        terms on the surface's (node, light) pairs are computed once (``Model.geometry``).
        """
        if self._values is None:
            self._values = np.empty((len(self.entry_col), BANDS))
        a, das, tr = self._values, [], self.trees
        for s, idx, start, J in self._groups:  # per surface: its model on all its nodes at once
            model, n = self.models[s], len(idx)
            t0 = self.layout.theta_offset[s]
            th = np.asarray(theta[t0:self.layout.theta_offset[s + 1]], dtype=np.float64)
            P = len(th)
            hit = self._last.get(s)
            if hit is not None and (P == 0 or (np.array_equal(hit[0], th) and (hit[1] is not None or not grad))):
                if grad and P:
                    das.append((self._shaped_entries(s), hit[1], t0))
                continue
            w = self.weight[idx]  # (n, K, 3)
            K = w.shape[1]
            if s not in self._geometry:
                # All lights stacked along N as the models expect: the rows of this system's nodes
                # among the surface's terms on the trees (formed once per trees, the same numbers).
                from reflab.inverse.forward.rendering import surface_terms

                terms, every = surface_terms(tr, model, s)
                at = (np.searchsorted(every, self.node[idx])[:, None] * K + np.arange(K)[None, :]).ravel()
                self._geometry[s] = tuple(t[at] for t in terms)
            g, dg = model.g_and_dg_on(th, self._geometry[s], grad=grad and P > 0)
            g = g.reshape(n, K, J)
            block = a[start:start + n * J].reshape(n, J, BANDS)
            kd = self._kd_index(s)
            for j in (range(J) if hit is None else model.shaped):  # the others keep their values
                block[:, j] = _light_sum(w, g[:, :, j])
                if j == kd:
                    block[:, j] *= self.albedo[idx]
            dacc = None
            if grad and P:
                # (P, 3, n·|shaped|), in the order of _shaped_entries: contiguous per (θ, band).
                dg = dg.reshape(n, K, J, P)
                shaped = model.shaped
                dacc = np.empty((P, BANDS, n, len(shaped)))
                for i, j in enumerate(shaped):
                    for p in range(P):
                        d = _light_sum(w, dg[:, :, j, p])
                        if j == kd:
                            d *= self.albedo[idx]
                        dacc[p, :, :, i] = d.T
                dacc = dacc.reshape(P, BANDS, -1)
                das.append((self._shaped_entries(s), dacc, t0))
            self._last[s] = (th.copy(), dacc)
        if not grad:
            return a
        return a, das

    def _shaped_entries(self, s: int) -> tuple:
        """The entries (indices) of surface ``s``'s θ-shaped columns, node by node, and their rows and columns."""
        cache = self.__dict__.setdefault("_shaped_cache", {})
        if s not in cache:
            start, n, J = next((st, len(i), J) for t, i, st, J in self._groups if t == s)
            shaped = np.asarray(self.models[s].shaped, dtype=np.int64)
            sel = (start + np.arange(n)[:, None] * J + shaped[None, :]).ravel()
            cache[s] = (sel, self.entry_row[sel], self.entry_col[sel])
        return cache[s]

    def _kd_index(self, s: int):
        """Index of ``kd`` among surface ``s``'s linear parameters when a known texture scales it."""
        if self.albedo is None or "kd" not in self.models[s].linear:
            return None
        return self.models[s].linear.index("kd")

    def matrices(self, theta) -> list:
        """A_c(θ) for each band: CSR (rows × columns) (:meth:`matrices_and_grad`'s when it kept them)."""
        kept = self._kept(theta)
        return kept[0] if kept is not None else self._assemble(self._entries(theta, grad=False))

    #: :meth:`matrices_and_grad` keeps its last results for this many θ: the fit's bookkeeping (σ,
    #: holding, outliers) asks again for the θ of the search's last accepted step or its last trial.
    KEEP = 2

    def _kept(self, theta):
        key = np.asarray(theta, dtype=np.float64).tobytes()
        for k, value in getattr(self, "_memo", ()):
            if k == key:
                return value
        return None

    def _assemble(self, a) -> "Matrices":
        import scipy.sparse as sp

        if self._slot_order is None:
            # Entries that share a slot (two nodes of one pixel with one monomial) are summed; where
            # none do, the CSR data is a permutation of the entries.
            self._slot_order = np.argsort(self.entry_slot, kind="stable") if self._n_slots == len(self.entry_slot) else False
        out = Matrices()
        for c in range(BANDS):
            if self._slot_order is not False:
                data = a[self._slot_order, c]
            else:
                data = np.bincount(self.entry_slot, weights=a[:, c], minlength=self._n_slots)
            out.append(sp.csr_matrix((data, self._indices, self._indptr), shape=(self.n_rows, self.n_columns)))
        return out

    def matrices_and_grad(self, theta):
        """A_c(θ) and a function ``grad(residual, y) -> (Q,)`` = Σ_c residual_c · ∂A_c/∂θ_q · y_c.

        Parameters
        ----------
        theta : (Q,) array_like
            Flat nonlinear parameters in the models' natural units.

        Returns
        -------
        A : list of 3 CSR matrices
        grad : callable
            ``grad(residual (3, R), y (3, C))`` returns the derivative of ``Σ_c residualᵀ A_c y_c``
            with respect to each θ (residual held fixed), and ``grad.images(y, which=None)`` returns
            the (Q, 3, R) image derivatives ``∂(A_c y_c)/∂θ_q`` (only the θ ``which`` names, in its order);
            with ``compact=True``, ``(images (Q, 3, R'), rows (R',))``: only the used-pixel rows
            where those θ act (:meth:`_theta_rows`; zero elsewhere).
        """
        kept = self._kept(theta)
        if kept is not None:
            return kept
        a, das = self._entries(theta, grad=True)
        A = self._assemble(a)
        rows, cols = self.entry_row, self.entry_col
        Q = self.layout.n_theta

        R = self.n_rows

        def images(y, which=None, compact=False):
            # Only the θ asked for (``which``): the others' (3, R) images would be allocated and
            # filled for nothing (a 640x480 fit frees two or three of its six θ at a time).
            which = np.arange(Q) if which is None else np.asarray(which, dtype=np.int64)
            at = np.full(Q, -1)
            at[which] = np.arange(len(which))
            used, local = self._theta_rows(which) if compact else (None, rows)
            n = R if used is None else len(used)
            out = np.zeros((len(which), BANDS, n))
            for (sel, _, col), d, q0 in das:  # per surface; the 3 bands in one bincount
                wanted = [p for p in range(d.shape[0]) if at[q0 + p] >= 0]
                if not wanted:
                    continue
                slot = (local[sel][None, :] + n * np.arange(BANDS)[:, None]).ravel()
                yc = np.take(y, col, axis=1)  # (3, n)
                for p in wanted:
                    out[at[q0 + p]] = np.bincount(slot, weights=(d[p] * yc).ravel(), minlength=BANDS * n).reshape(BANDS, n)
            return (out, used) if compact else out

        def grad(residual, y):
            out = np.zeros(Q)
            for (_, row, col), d, q0 in das:
                wres = np.take(residual, row, axis=1) * np.take(y, col, axis=1)  # (3, n)
                # einsum's own loop: a (1 × n)·(n) BLAS product is several times slower here.
                out[q0:q0 + d.shape[0]] = np.einsum("pk,k->p", d.reshape(d.shape[0], -1), wres.ravel())
            return out

        grad.images = images
        memo = getattr(self, "_memo", [])
        self._memo = [(np.asarray(theta, dtype=np.float64).tobytes(), (A, grad))] + memo[: self.KEEP - 1]
        return A, grad

    def _theta_rows(self, which) -> tuple[np.ndarray, np.ndarray]:
        """The rows (sorted) where the θ ``which`` act, and each entry's index among them (−1: none).

        A surface's θ moves only the pixels its nodes reach (a small cube's shininess: a few
        thousand of 300 000), so the θ blocks of the normal matrix need only those rows.
        """
        key = tuple(int(q) for q in which)
        cache = self._theta_rows_cache
        if key not in cache:
            lay = self.layout
            owners = {s for s in range(len(self.models)) for q in key
                      if lay.theta_offset[s] <= q < lay.theta_offset[s + 1]}
            touched = np.zeros(self.n_rows, dtype=bool)
            for s, idx, start, J in self._groups:
                if s in owners:
                    touched[self.entry_row[start:start + len(idx) * J]] = True
            used = np.flatnonzero(touched)
            at = np.full(self.n_rows, -1, dtype=np.int64)
            at[used] = np.arange(len(used))
            cache[key] = (used, at[self.entry_row])
        return cache[key]

    # ------------------------------------------------------------------ monomials
    def y(self, x, s) -> np.ndarray:
        """Monomial values (3, C) from linear parameters ``x`` (X, 3) and factors ``s`` (F, 3)."""
        return (np.asarray(x)[self.col_x] * self.factor_products(s)).T

    def factor_products(self, s, skip: int | None = None) -> np.ndarray:
        """Π_f s_f^e of each column (C, 3), optionally leaving factor ``skip`` out."""
        ext = np.ones((len(self._used) + 1, BANDS))  # the last row: an absent factor (1)
        ext[:-1] = np.asarray(s)[self._used]
        if skip is not None:
            ext[:-1][self._used == skip] = 1.0
        idx = self._factor_index
        out = ext[idx[:, 0]]
        for k in range(1, idx.shape[1]):
            out *= ext[idx[:, k]]
        return out

    def render(self, theta, x, s) -> np.ndarray:
        """Model radiance (3, R) of the used pixels for the given parameters."""
        y = self.y(x, s)
        return np.stack([A @ y[c] for c, A in enumerate(self.matrices(theta))])
