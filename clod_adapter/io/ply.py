"""Read and write 3DGS checkpoints in the INRIA .ply layout (plus the CLoD ``sigma_d`` extension).

Layout (graphdeco-inria/gaussian-splatting, ``scene/gaussian_model.py`` ``save_ply`` /
``construct_list_of_attributes``), one ``vertex`` element of float32 properties in this order::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..f_rest_{3(K-1)-1}  opacity  scale_0..2  rot_0..3

``f_rest`` is channel-major: property ``f_rest_{c*(K-1)+k}`` holds SH coefficient k+1 of colour
channel c (the official code saves ``features_rest.transpose(1, 2).flatten(1)``), ``opacity`` is
the logit, ``scale_*`` the log of the standard deviations, ``rot_*`` the quaternion w, x, y, z
(unnormalised). The extended file of this project appends one float property ``sigma_d``
(CLoD-GS distance decay, Cheng et al., ICLR 2026, Eq. 2), and, when the model has them, the
level gains ``opacity_gain``, ``scale_gain``, ``f_dc_gain_0..2`` (only those present; see
:class:`clod_adapter.gaussians.Gaussians`). The LoD settings travel as one header comment
``clod_lod max_sv=5 tau=0.005 eps=1e-08 fade=window fade_width=0.75``; viewers that do not know
them ignore both.

Reading selects the properties by name (order does not matter; ASCII and big-endian files are
read as plyfile parses them); writing always produces the exact INRIA order, binary little
endian. Any other scalar vertex property (e.g. MaskGaussian's ``masks_0``/``masks_1``) is kept
in :attr:`Gaussians.extra <clod_adapter.gaussians.Gaussians>` and written back after the known
ones, with its type; list properties and other elements are dropped.
"""
from __future__ import annotations

import os
from pathlib import Path
from dataclasses import replace
from typing import Optional, Union

import numpy as np
import plyfile
import torch
from numpy.lib import recfunctions as rfn

from clod_adapter.errors import InputError
from clod_adapter.gaussians import Gaussians
from clod_adapter.io.atomic import atomic_write
from clod_adapter.lod_settings import LodSettings

__all__ = ["PlyFormatError", "read_ply", "write_ply", "ply_property_names", "ply_vertex_dtype", "ply_comments",
           "tier_element", "tier_chain_of", "TIER_COMMENT", "TIER_KEYS", "UNLINKED_TIERS"]

PathLike = Union[str, "os.PathLike[str]"]

_F_REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}  # number of f_rest properties -> SH degree
#: .ply properties of the level gains, by Gaussians field.
GAIN_PROPERTIES = {"opacity_logit_gain": ["opacity_gain"], "log_scale_gain": ["scale_gain"],
                   "sh0_gain": ["f_dc_gain_0", "f_dc_gain_1", "f_dc_gain_2"]}
LOD_COMMENT = "clod_lod"
#: the element holding an adapted model's parent tier (``Gaussians.parents``): the vertex
#: element's layout; viewers that read only ``vertex`` draw the model without it
PARENT_ELEMENT = "lod_parent"
#: the header comment holding tier ``k``'s own settings (k >= 1): its hand-over to tier ``k + 1``,
#: ``clod_lod_tier k tier_s_v=.. tier_start=.. tier_fade=..``, and its window ``fade_width=..`` where it
#: is not the model's
TIER_COMMENT = "clod_lod_tier"
#: a tier's hand-over to the next tier, in its ``clod_lod_tier`` comment when it hands over again
HAND_OVER_KEYS = ("tier_s_v", "tier_start", "tier_fade")
#: the settings a ``clod_lod_tier`` comment may hold
TIER_KEYS = HAND_OVER_KEYS + ("fade_width",)


#: why a file whose merged tiers are not linked into a merge tree is not read for drawing
#: (:func:`read_ply`)
UNLINKED_TIERS = ("its merged tiers are not linked into a merge tree (written with --tier-draw chain, which is "
                  "no longer drawn, or a merged tier's own file in a clod-adapt parents/ folder); re-run clod-adapt")


def tier_element(k: int) -> str:
    """The element holding tier ``k >= 1`` of a model (:func:`clod_adapter.lod.draw.tier_chain`):
    ``lod_parent`` for the first parent tier, ``lod_parent_k`` for the next ones."""
    return PARENT_ELEMENT if k == 1 else f"{PARENT_ELEMENT}_{k}"


def tier_chain_of(gaussians: Gaussians) -> list:
    """``[gaussians, gaussians.parents, ...]``: the model and the parent tiers a file holds."""
    out = [gaussians]
    while out[-1].parents is not None:
        out.append(out[-1].parents)
    return out


def lod_comment(settings: LodSettings) -> str:
    """The header comment that stores ``settings`` (``clod_lod key=value ...``)."""
    items = {k: v for k, v in settings.to_dict().items()
             if (not k.startswith("tier_") or settings.tier_s_v > 0)  # a model without a tier: no tier keys
             and (k != "tree" or v)}  # written only where set
    return LOD_COMMENT + " " + " ".join(f"{k}={v!r}" if isinstance(v, float) else f"{k}={v}"
                                        for k, v in items.items())


def parse_lod_comment(comments, path: PathLike = "<ply>") -> "LodSettings | None":
    """The :class:`LodSettings` of a ``clod_lod`` header comment, or None when there is none.

    Raises:
        PlyFormatError: the comment is malformed or holds invalid values.
    """
    for c in comments:
        tok = c.split()
        if not tok or tok[0] != LOD_COMMENT:
            continue
        kw = {}
        try:
            for item in tok[1:]:
                k, v = item.split("=", 1)
                if k in ("max_sv", "tau", "eps", "fade_width", "level_max", "tier_s_v", "tier_start", "tier_fade"):
                    kw[k] = float(v)
                elif k == "fade":
                    kw[k] = v
                elif k in ("count_mix", "tree"):  # count_mix: written by earlier versions, no longer drawn
                    if v not in ("True", "False"):
                        raise ValueError(f"{k} must be True or False, got {v!r}")
                    if k == "tree":
                        kw[k] = v == "True"
            return LodSettings(**kw)
        except (ValueError, TypeError) as e:
            raise PlyFormatError(path, f"bad '{LOD_COMMENT}' header comment {c!r}: {e}") from None
    return None


class PlyFormatError(InputError):
    """A .ply file is not a readable 3DGS checkpoint; the message is ``"<path>: <problem>"``."""

    def __init__(self, path: PathLike, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


def ply_property_names(sh_degree: int, *, with_normals: bool = True, with_sigma_d: bool = False) -> list[str]:
    """The vertex property names, in the INRIA order, for a model of SH degree ``sh_degree``.

    Raises:
        ValueError: ``sh_degree`` is not 0..3.
    """
    if sh_degree not in (0, 1, 2, 3):
        raise ValueError(f"SH degree must be 0..3, got {sh_degree}")
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    names = ["x", "y", "z"]
    if with_normals:
        names += ["nx", "ny", "nz"]
    names += [f"f_dc_{i}" for i in range(3)]
    names += [f"f_rest_{i}" for i in range(n_rest)]
    names += ["opacity"]
    names += [f"scale_{i}" for i in range(3)]
    names += [f"rot_{i}" for i in range(4)]
    if with_sigma_d:
        names += ["sigma_d"]
    return names


def open_ply(path: Path) -> "plyfile.PlyData":
    """``plyfile.PlyData.read`` (memory-mapped) with every failure turned into one
    :class:`PlyFormatError` naming the file; counts are checked against the file size first, so a
    hostile header cannot make plyfile allocate or divide by zero.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PlyFormatError: empty, impossible element counts, bad header, truncated data.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    size = path.stat().st_size
    if size == 0:
        raise PlyFormatError(path, "file is empty")
    _check_element_counts(path, size)
    try:
        return plyfile.PlyData.read(str(path))
    except plyfile.PlyElementParseError as e:
        raise PlyFormatError(path, f"cannot read element data (truncated or corrupt file?): {e}") from None
    except (plyfile.PlyParseError, ValueError, EOFError, UnicodeDecodeError, IndexError,
            OverflowError, MemoryError, TypeError, KeyError) as e:
        raise PlyFormatError(path, f"not a valid PLY file: {e or type(e).__name__}") from None


def _refuse_nonfinite(path: Path, named: dict) -> None:
    """Raise PlyFormatError naming the arrays of ``named`` (label -> array) that hold NaN/Inf."""
    bad = {k: a for k, a in named.items() if not np.isfinite(a).all()}
    if not bad:
        return
    counts = {"NaN": 0, "+Inf": 0, "-Inf": 0}
    for a in bad.values():
        counts["NaN"] += int(np.isnan(a).sum())
        counts["+Inf"] += int(np.isposinf(a).sum())
        counts["-Inf"] += int(np.isneginf(a).sum())
    what = ", ".join(f"{c} {k}" for k, c in counts.items() if c)
    raise PlyFormatError(path, f"non-finite values ({what}) in {', '.join(bad)}; pass allow_nonfinite=True to keep them")


def _extra_properties(vertex, data, degree: int) -> dict:
    """Every scalar vertex property the layout does not name, in file order, as an [N] tensor of
    its own type (native byte order; one small copy each)."""
    known = set(ply_property_names(degree, with_normals=True, with_sigma_d=True))
    known.update(v for props in GAIN_PROPERTIES.values() for v in props)
    extra = {}
    for p in vertex.properties:
        if isinstance(p, plyfile.PlyListProperty) or p.name in known or p.name.startswith("f_rest_"):
            continue
        a = np.asarray(data[p.name])
        extra[p.name] = torch.from_numpy(np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("=")))
    return extra


def _columns(src: np.ndarray, where: dict, wanted: list, n: int, n_rest: int, with_sigma_d: bool,
             gains_present: dict) -> tuple:
    """The attributes as fresh C-contiguous float32 arrays (never views of the memory map):
    (means, sh0, shN (channel-major f_rest reordered), opacity, log_scales, quats, sigma_d or
    None, gains)."""
    km1 = n_rest // 3

    def block(first: str, count: int) -> np.ndarray:
        """[N, count] columns ``first``.. as a view of ``src`` where possible (never returned)."""
        start = wanted.index(first)
        idx = [where[name] for name in wanted[start : start + count]]
        if idx == list(range(idx[0], idx[0] + count)):
            return src[:, idx[0] : idx[0] + count]
        return src[:, idx]

    def own(a: np.ndarray) -> np.ndarray:  # a fresh C-contiguous float32 copy (never the memmap)
        with np.errstate(over="ignore"):  # float64 beyond float32 -> inf, reported below
            return np.array(a, dtype=np.float32, order="C", copy=True)

    means = own(block("x", 3))
    sh0 = own(block("f_dc_0", 3)).reshape(n, 1, 3)
    if km1:
        shN = own(block("f_rest_0", n_rest).reshape(n, 3, km1).transpose(0, 2, 1))
    else:
        shN = np.zeros((n, 0, 3), dtype=np.float32)
    opacity = own(block("opacity", 1)).reshape(n)
    log_scales = own(block("scale_0", 3))
    quats = own(block("rot_0", 4))
    sigma_d = own(block("sigma_d", 1)).reshape(n) if with_sigma_d else None
    gains = {k: own(block(v[0], len(v))) for k, v in gains_present.items()}
    if "sh0_gain" in gains:
        gains["sh0_gain"] = gains["sh0_gain"].reshape(n, 1, 3)
    for k in ("opacity_logit_gain", "log_scale_gain"):
        if k in gains:
            gains[k] = gains[k].reshape(n)
    return means, sh0, shN, opacity, log_scales, quats, sigma_d, gains


def read_ply(path: PathLike, *, allow_nonfinite: bool = False, unlinked_tiers: bool = False) -> Gaussians:
    """Read a 3DGS checkpoint .ply (INRIA layout, optionally with ``sigma_d``) into ``Gaussians``.

    Required vertex properties: x y z, f_dc_0..2, f_rest_0..M-1 with M in {0, 9, 24, 45}
    (SH degree 0..3), opacity, scale_0..2, rot_0..3. Optional: nx ny nz (ignored), ``sigma_d``,
    the level gains. Every other scalar vertex property goes, in file order, to ``extra`` as an
    [N] tensor of its own type (not checked for NaN/Inf). A second element ``lod_parent``
    (:data:`PARENT_ELEMENT`, the same layout) is the model's parent tier, read into
    ``Gaussians.parents`` (docs/method.md "Merged tiers"); ``lod_parent_2``, ... are the next
    tiers (:func:`tier_element`), each a ``parents`` of the one before, their hand-over settings
    in ``clod_lod_tier k`` comments. Such tiers are drawn only linked into a merge tree
    (``tree=True`` in the ``clod_lod`` comment, docs/lod_rule.md "The file"); a file whose tiers
    are not (written with ``clod-adapt --tier-draw chain``, which is no longer drawn, or a merged
    tier's own file in a ``parents/`` folder) is refused unless ``unlinked_tiers``.
    Any numeric property type is accepted and converted to float32 (float32 input is copied
    bit-exactly). The file is memory-mapped (plyfile's default) and converted in one vectorised
    pass; the input is never modified.

    Args:
        path: the .ply file.
        allow_nonfinite: keep NaN/Inf values instead of raising.
        unlinked_tiers: read merged tiers that are not linked into a merge tree (the tiers
            ``clod-adapt`` links, :func:`clod_adapter.lod.tree.build`; not drawn as they are).

    Returns:
        ``Gaussians`` with contiguous float32 CPU tensors: means [N,3], quats [N,4] (wxyz, raw),
        log_scales [N,3], opacity_logits [N], sh0 [N,1,3], shN [N,K-1,3] (reordered from the
        channel-major f_rest), sigma_d [N] or None, the gains present, ``extra``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        PlyFormatError: not a parseable .ply (empty, bad header, truncated data), no ``vertex``
            element, a required property missing, an f_rest count that is no SH degree, a NaN/Inf
            value (unless ``allow_nonfinite``), a ``lod_parent`` element without ``sigma_d``,
            the vertex element's SH degree or a ``tier_s_v`` in the header, or merged tiers not
            linked into a merge tree (unless ``unlinked_tiers``; :data:`UNLINKED_TIERS`).
    """
    path = Path(path)
    ply = open_ply(path)

    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise PlyFormatError(path, f"no 'vertex' element (elements: {', '.join(names) or 'none'})")
    lod_settings = parse_lod_comment(getattr(ply, "comments", []), path)
    tiers = [_read_element(path, ply["vertex"], lod_settings, allow_nonfinite)]
    hand = _tier_comments(getattr(ply, "comments", []), path)
    k = 1
    while tier_element(k) in names:
        above = tiers[-1]
        if above.sigma_d is None or above.lod is None or above.lod.tier_s_v <= 0:
            raise PlyFormatError(path, f"a '{tier_element(k)}' element without an adapted tier above it and a "
                                       f"'tier_s_v' for that tier in the '{LOD_COMMENT}' comments")
        tier = _read_element(path, ply[tier_element(k)], _parent_settings(lod_settings, hand.get(k), path),
                             allow_nonfinite)
        if tier.sigma_d is None or tier.sh_degree != tiers[0].sh_degree:
            raise PlyFormatError(path, f"the '{tier_element(k)}' element needs sigma_d and the vertex "
                                       f"element's SH degree")
        tiers.append(tier)
        k += 1
    stray = [n for n in names if n.startswith(PARENT_ELEMENT) and n not in [tier_element(i) for i in range(1, k)]]
    if stray:
        raise PlyFormatError(path, f"element '{stray[0]}' without '{tier_element(k)}' before it")
    if tiers[-1].lod is not None and tiers[-1].lod.tier_s_v > 0 and len(tiers) > 1:
        raise PlyFormatError(path, f"a '{TIER_COMMENT} {k - 1}' comment without a '{tier_element(k)}' element")
    if lod_settings is not None and lod_settings.tree:
        _check_tree(path, tiers)
    elif len(tiers) > 1 and not unlinked_tiers:
        raise PlyFormatError(path, UNLINKED_TIERS)
    g = tiers[-1]
    for above in reversed(tiers[:-1]):
        g = replace(above, parents=g)
    return g


def _check_tree(path: Path, tiers: list) -> None:
    """A ``tree=True`` file's tree (docs/lod_rule.md "The file"): every element but the last has an
    integer ``parent`` property naming a row of the next element, every row of the next element is
    some row's parent, and every element has finite float ``exit`` and ``d_ref`` properties, but
    for an ``exit`` of +inf marking a parent's lead child: where an element marks any, exactly one
    child of each parent (a file without marks gets its leads chosen when drawn,
    ``clod_adapter.lod.tree.leads``).

    Raises:
        PlyFormatError: the file says ``tree=True`` and one of these does not hold.
    """
    if len(tiers) < 2:
        raise PlyFormatError(path, "'tree=True' in the 'clod_lod' comment but no 'lod_parent' element")
    for k, (tier, above) in enumerate(zip(tiers, tiers[1:])):
        name = "vertex" if k == 0 else tier_element(k)
        p = tier.extra.get("parent")
        if p is None or p.dtype.is_floating_point:
            raise PlyFormatError(path, f"'tree=True' but element '{name}' has no integer 'parent' property")
        p = p.long()
        if p.numel() and (int(p.min()) < 0 or int(p.max()) >= len(above)):
            raise PlyFormatError(path, f"element '{name}': a 'parent' outside 0..{len(above) - 1} "
                                       f"(the rows of '{tier_element(k + 1)}')")
        if bool((torch.bincount(p, minlength=len(above)) == 0).any()):
            raise PlyFormatError(path, f"element '{tier_element(k + 1)}': a row that is no row's parent")
    for k, tier in enumerate(tiers):
        name = "vertex" if k == 0 else tier_element(k)
        for key in ("exit", "d_ref"):
            x = tier.extra.get(key)
            marks = key == "exit" and k + 1 < len(tiers)  # +inf marks a parent's lead child
            ok = x is not None and x.dtype.is_floating_point
            lead = torch.isposinf(x) if ok and marks else None
            if not ok or not bool((torch.isfinite(x) if lead is None else torch.isfinite(x) | lead).all()):
                raise PlyFormatError(path, f"'tree=True' but element '{name}' has no finite float '{key}' property"
                                           + (" (+inf only for a parent's lead)" if marks else ""))
            if lead is not None and bool(lead.any()):
                n = torch.bincount(tier.extra["parent"].long()[lead], minlength=len(tiers[k + 1]))
                if bool((n != 1).any()):
                    j = int(torch.nonzero(n != 1)[0])
                    raise PlyFormatError(path, f"element '{name}': row {j} of '{tier_element(k + 1)}' has "
                                               f"{int(n[j])} lead children (an 'exit' of +inf), not 1")


def _tier_comments(comments, path: Path) -> dict:
    """``{k: {tier_s_v, tier_start, tier_fade, fade_width}}`` (those given) of the ``clod_lod_tier k ...``
    header comments."""
    out = {}
    for c in comments:
        tok = c.split()
        if not tok or tok[0] != TIER_COMMENT:
            continue
        try:
            out[int(tok[1])] = {k: float(v) for k, v in (item.split("=", 1) for item in tok[2:])
                                if k in TIER_KEYS}
        except (ValueError, IndexError) as e:
            raise PlyFormatError(path, f"bad '{TIER_COMMENT}' header comment {c!r}: {e}") from None
    return out


def _parent_settings(settings: LodSettings, own: Optional[dict] = None, path: PathLike = "<ply>") -> LodSettings:
    """A parent tier's settings: the model's, with the tier's own hand-over to the next tier and
    window width (``own``: from its ``clod_lod_tier`` comment) or none."""
    try:
        return replace(settings, **{"tier_s_v": 0.0, "tier_start": 1.0, "tier_fade": LodSettings.tier_fade,
                                    **(own or {})})
    except ValueError as e:
        raise PlyFormatError(path, f"bad '{TIER_COMMENT}' values: {e}") from None


def _read_element(path: Path, vertex, lod_settings, allow_nonfinite: bool) -> Gaussians:
    """One element of INRIA-layout rows (``vertex``, or the parent tier) as :class:`Gaussians`."""
    data = vertex.data  # numpy structured array (a memmap for binary files)
    scalar_fields = {
        p.name for p in vertex.properties if not isinstance(p, plyfile.PlyListProperty)
    }

    n_rest = sum(1 for f in scalar_fields if f.startswith("f_rest_"))
    if n_rest not in _F_REST_COUNTS:
        raise PlyFormatError(
            path, f"{n_rest} f_rest_* properties match no SH degree (expected 0, 9, 24 or 45 for degree 0..3)"
        )
    degree = _F_REST_COUNTS[n_rest]
    with_sigma_d = "sigma_d" in scalar_fields
    gains_present = {k: v for k, v in GAIN_PROPERTIES.items() if v[0] in scalar_fields}
    wanted = ply_property_names(degree, with_normals=False, with_sigma_d=with_sigma_d)
    for props in gains_present.values():
        wanted += props
    missing = [f for f in wanted if f not in scalar_fields]
    if missing:
        shown = ", ".join(missing[:8]) + (", ..." if len(missing) > 8 else "")
        raise PlyFormatError(path, f"{vertex.name} element lacks required propert{'y' if len(missing) == 1 else 'ies'} {shown}")

    extra = _extra_properties(vertex, data, degree)

    n = len(data)
    src, where = _as_2d(data, wanted)  # [N, F'] view (or one converted copy) + column of each name
    del data, vertex  # the memory map stays alive only through ``src`` until we are done
    means, sh0, shN, opacity, log_scales, quats, sigma_d, gains = _columns(src, where, wanted, n, n_rest,
                                                                          with_sigma_d, gains_present)
    del src

    if not allow_nonfinite:
        named = {"means (x y z)": means, "sh0 (f_dc_*)": sh0, "shN (f_rest_*)": shN, "opacity": opacity,
                 "log_scales (scale_*)": log_scales, "quats (rot_*)": quats}
        if sigma_d is not None:
            named["sigma_d"] = sigma_d
        named.update({f"{k} ({GAIN_PROPERTIES[k][0]})": v for k, v in gains.items()})
        _refuse_nonfinite(path, named)

    t = torch.from_numpy
    return Gaussians(
        means=t(means),
        quats=t(quats),
        log_scales=t(log_scales),
        opacity_logits=t(opacity),
        sh0=t(sh0),
        shN=t(shN),
        sigma_d=t(sigma_d) if sigma_d is not None else None,
        lod=lod_settings if sigma_d is not None else None,
        extra=extra,
        **{k: t(v) for k, v in gains.items()},
    )


def _check_element_counts(path: Path, size: int) -> None:
    """Reject element counts plyfile would choke on before it sees them: a negative count (numpy
    dies with SIGFPE on a property-less element of count -1) or more rows than the file has bytes
    (each row of an element with properties takes at least one byte in every format; plyfile
    would otherwise allocate the claimed rows first, e.g. 8 bytes x 10^12 for a list property).
    Anything else malformed is left to plyfile's own header parser."""
    with open(path, "rb") as f:
        head = f.read(1 << 20)
    end = head.find(b"end_header")
    if end < 0:
        return
    current = None  # [name, count, number of properties]
    elements = []
    for line in head[:end].split(b"\n"):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == b"element" and len(tok) == 3:
            try:
                count = int(tok[2])
            except ValueError:
                current = None
                continue
            current = [tok[1].decode("latin-1"), count, 0]
            elements.append(current)
        elif tok[0] == b"property" and current is not None:
            current[2] += 1
    for name, count, nprops in elements:
        if count < 0:
            raise PlyFormatError(path, f"element {name!r} has a negative count ({count})")
        if count > (size if nprops else 1 << 62):
            raise PlyFormatError(path, f"element {name!r} claims {count} rows, more than the file "
                                       f"({size} bytes) can hold (truncated or corrupt header?)")


def _as_2d(data: np.ndarray, wanted: list[str]) -> tuple[np.ndarray, dict[str, int]]:
    """A 2D array holding the ``wanted`` fields of structured ``data`` and each name's column.

    When every field of the record has one scalar dtype and the records are packed (the usual
    all-float32 checkpoint, either byte order), this is a zero-copy [N, F] view of the whole
    record; otherwise the wanted fields are converted once with ``structured_to_unstructured``.
    """
    dt = data.dtype
    n = len(data)
    fields = dt.names or ()
    first = dt.fields[fields[0]][0] if fields else None
    uniform = (
        first is not None
        and first.shape == ()
        and first.kind in "fiu"
        and all(dt.fields[f][0] == first for f in fields)
        and all(dt.fields[f][1] == i * first.itemsize for i, f in enumerate(fields))
        and dt.itemsize == len(fields) * first.itemsize
        and data.ndim == 1
        and (n == 0 or data.strides[0] == dt.itemsize)
    )
    if uniform:
        flat = np.ndarray(shape=(n, len(fields)), dtype=first, buffer=data, offset=0) if n else np.zeros(
            (0, len(fields)), dtype=first
        )
        return flat, {f: i for i, f in enumerate(fields)}
    if n == 0:
        return np.zeros((0, len(wanted)), dtype=np.float32), {f: i for i, f in enumerate(wanted)}
    arr = rfn.structured_to_unstructured(data[wanted], dtype=np.float32, copy=True)
    return arr, {f: i for i, f in enumerate(wanted)}

def _as_f32(x: torch.Tensor) -> np.ndarray:
    return x.detach().to(device="cpu", dtype=torch.float32).numpy()


def _float_layout(g: Gaussians, with_normals: bool) -> tuple[list[str], list[str]]:
    """The float32 property names :func:`write_ply` writes for ``g`` (INRIA order, ``sigma_d``,
    gains) and the gain fields present."""
    names = ply_property_names(g.sh_degree, with_normals=with_normals, with_sigma_d=g.sigma_d is not None)
    gain_fields = [k for k in GAIN_PROPERTIES if getattr(g, k) is not None]
    for k in gain_fields:
        names += GAIN_PROPERTIES[k]
    return names, gain_fields


def ply_vertex_dtype(gaussians: Gaussians, *, with_normals: bool = True) -> np.dtype:
    """The packed little-endian structured dtype of one vertex row as :func:`write_ply` writes
    ``gaussians``: the float32 properties in order, then each ``extra`` with its own type.

    Raises:
        ValueError: an ``extra`` name is also a property of the layout written.
    """
    names, _ = _float_layout(gaussians, with_normals)
    descr = [(name, "<f4") for name in names]
    if gaussians.extra:
        clash = [k for k in gaussians.extra if k in names]
        if clash:
            raise ValueError(f"Gaussians.extra holds {', '.join(clash)}, a property of the layout written")
        descr += [(k, torch.empty(0, dtype=v.dtype).numpy().dtype.newbyteorder("<"))
                  for k, v in gaussians.extra.items()]
    return np.dtype(descr)


def ply_comments(gaussians: Gaussians) -> list[str]:
    """The header comments :func:`write_ply` writes: the ``clod_lod`` settings of an adapted model."""
    g = gaussians
    out = [lod_comment(g.lod)] if (g.lod is not None and g.sigma_d is not None) else []
    for k, t in enumerate(tier_chain_of(g)[1:], start=1):  # each parent tier's own settings
        if t.lod is None or g.lod is None:
            continue
        keys = list(HAND_OVER_KEYS) if t.lod.tier_s_v > 0 else []
        keys += ["fade_width"] if t.lod.fade_width != g.lod.fade_width else []
        if keys:
            out.append(f"{TIER_COMMENT} {k} " + " ".join(f"{n}={getattr(t.lod, n)!r}" for n in keys))
    return out


def write_ply(path: PathLike, gaussians: Gaussians, *, with_normals: bool = True) -> Path:
    """Write ``gaussians`` as an INRIA-layout .ply, binary little endian, atomically.

    Property order: x y z [nx ny nz] f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3, then
    ``sigma_d`` when ``gaussians.sigma_d`` is not None (the extended file), then the level gains
    present (``opacity_gain``, ``scale_gain``, ``f_dc_gain_0..2``), then ``gaussians.extra`` by
    name with its own type (e.g. ``masks_0``, ``masks_1``); ``gaussians.lod`` is written as the
    ``clod_lod`` header comment; ``gaussians.parents`` (the parent tier) as a second element,
    ``lod_parent``, in the same layout, its own parents as ``lod_parent_2`` and so on
    (:func:`tier_element`; each tier's hand-over to the next in a ``clod_lod_tier k`` comment). Normals are written
    as zeros (as the official ``save_ply``). ``shN`` [N,K-1,3] is written channel-major
    (``f_rest_{c*(K-1)+k}``). Tensors on any device / dtype are converted to float32 CPU; the
    vertex block is one contiguous structured array, so read -> write -> read is bit-exact.

    Args:
        path: output file (parent directory must exist); replaced atomically.
        gaussians: the model.
        with_normals: include the (zero) nx ny nz properties, as the INRIA trainer does.

    Returns:
        ``Path(path)``.

    Raises:
        FileNotFoundError: the parent directory does not exist.
        ValueError: an ``extra`` name is also a property of the layout written; a parent tier
            without ``sigma_d`` on both models or without ``lod.tier_s_v > 0``.
    """
    path = Path(path)
    g = gaussians
    elements = [plyfile.PlyElement.describe(_vertex_rows(g, with_normals), "vertex")]
    tiers = tier_chain_of(g)
    for k, (above, tier) in enumerate(zip(tiers, tiers[1:]), start=1):
        if above.lod is None or above.lod.tier_s_v <= 0 or above.sigma_d is None or tier.sigma_d is None:
            raise ValueError("write_ply: a parent tier needs an adapted model and parents, and lod.tier_s_v > 0")
        elements.append(plyfile.PlyElement.describe(_vertex_rows(tier, with_normals), tier_element(k)))
    ply = plyfile.PlyData(elements, text=False, byte_order="<", comments=ply_comments(g))
    with atomic_write(path, "wb") as f:
        ply.write(f)
    return path


def _vertex_rows(g: Gaussians, with_normals: bool) -> np.ndarray:
    """The structured rows of one element (:func:`write_ply`'s layout)."""
    n = g.num_gaussians
    km1 = g.shN.shape[1]
    names, gain_fields = _float_layout(g, with_normals)
    vertex = np.empty(n, dtype=[(name, "<f4") for name in names])
    flat = vertex.view("<f4").reshape(n, len(names))  # a view: filling it fills ``vertex``

    i = 0

    def put(block: np.ndarray) -> None:
        nonlocal i
        w = block.shape[1]
        flat[:, i : i + w] = block
        i += w

    put(_as_f32(g.means))
    if with_normals:
        put(np.zeros((n, 3), dtype=np.float32))
    put(_as_f32(g.sh0).reshape(n, 3))
    if km1:
        put(_as_f32(g.shN).transpose(0, 2, 1).reshape(n, 3 * km1))
    put(_as_f32(g.opacity_logits).reshape(n, 1))
    put(_as_f32(g.log_scales))
    put(_as_f32(g.quats))
    if g.sigma_d is not None:
        put(_as_f32(g.sigma_d).reshape(n, 1))
    for k in gain_fields:
        put(_as_f32(getattr(g, k)).reshape(n, len(GAIN_PROPERTIES[k])))
    assert i == len(names)
    if g.extra:
        cols = {k: v.detach().cpu().numpy() for k, v in g.extra.items()}
        full = np.empty(n, dtype=ply_vertex_dtype(g, with_normals=with_normals))
        for name in names:
            full[name] = vertex[name]
        for k, a in cols.items():
            full[k] = a
        vertex = full
    return vertex
