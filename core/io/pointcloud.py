"""Point clouds with colour, normal, source view and master id: LAS/LAZ (laspy) and binary PLY, read and write.

LAS 1.4, point format 7 (XYZ, GPS time, RGB): colour scaled to 16 bits, the master image index in
``point_source_id``, the cardinal view code in ``user_data`` (index into :data:`VIEWS`), the ASPRS class in
``classification`` (0 until the surface stage classifies the points), normals as extra byte
dimensions ``nx, ny, nz`` (float32) and the CRS as WKT. ``.laz`` is written compressed (lazrs backend).
Coordinates are stored with a 1 mm scale and an offset at the cloud's minimum, so UTM coordinates keep
millimetres.

PLY is binary little-endian with ``x y z`` as double (float32 would lose centimetres at UTM coordinates),
``nx ny nz`` float, ``red green blue`` uchar, ``view`` uchar and ``master`` ushort; Blender and CloudCompare
read the standard fields and ignore the others.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.views import VIEWS
from ..pipeline.atomic import atomic_path


@dataclass(eq=False)
class PointCloud:
    """Dense points, one row per point.

    Attributes
    ----------
    xyz : (n, 3) float64 world coordinates
    rgb : (n, 3) uint8 colour
    normal : (n, 3) float32 unit normals (zeros when unknown)
    view : (n,) uint8 index into :data:`~..geometry.views.VIEWS` of the master's cardinal view
    master : (n,) uint16 index of the master image (into ``masters``)
    masters : image ids of the masters
    crs : EPSG:nnnn or WKT
    classification : (n,) uint8 ASPRS class codes (0: never classified)
    """

    xyz: np.ndarray
    rgb: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    master: np.ndarray
    masters: list[str] = field(default_factory=list)
    crs: str = ""
    classification: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, np.float64).reshape(-1, 3)
        n = len(self.xyz)
        self.rgb = np.asarray(self.rgb, np.uint8).reshape(n, 3)
        self.normal = np.asarray(self.normal, np.float32).reshape(n, 3)
        self.view = np.asarray(self.view, np.uint8).reshape(n)
        self.master = np.asarray(self.master, np.uint16).reshape(n)
        self.classification = (np.zeros(n, np.uint8) if self.classification is None
                               else np.asarray(self.classification, np.uint8).reshape(n))

    def __len__(self) -> int:
        return len(self.xyz)

    def subset(self, mask_or_index: np.ndarray) -> PointCloud:
        i = mask_or_index
        return PointCloud(self.xyz[i], self.rgb[i], self.normal[i], self.view[i], self.master[i],
                          list(self.masters), self.crs, self.classification[i])


def display_subset(cloud: PointCloud, n: int, seed: int = 0) -> PointCloud:
    """At most ``n`` points of ``cloud`` drawn at random (fixed ``seed``), in their original order: the light
    copy viewers and Blender show."""
    sub = np.random.default_rng(seed).choice(len(cloud), size=min(len(cloud), n), replace=False) if len(cloud) \
        else np.zeros(0, np.int64)
    return cloud.subset(np.sort(sub))


def write_las(path: str | Path, cloud: PointCloud) -> None:
    """Write ``cloud`` as LAS, or LAZ when ``path`` ends with ``.laz`` (atomically)."""
    import laspy

    header = laspy.LasHeader(point_format=7, version="1.4")
    header.add_extra_dims([laspy.ExtraBytesParams(name=c, type=np.float32) for c in ("nx", "ny", "nz")])
    lo = np.floor(cloud.xyz.min(axis=0)) if len(cloud) else np.zeros(3)
    header.offsets = lo
    header.scales = np.array([0.001, 0.001, 0.001])
    if cloud.crs:
        from ..geometry.crs import parse_crs

        header.add_crs(parse_crs(cloud.crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    rgb16 = cloud.rgb.astype(np.uint16) * 257
    las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    las.point_source_id = cloud.master
    las.classification = cloud.classification
    las.user_data = cloud.view
    las.nx, las.ny, las.nz = cloud.normal[:, 0], cloud.normal[:, 1], cloud.normal[:, 2]
    path = Path(path)
    with atomic_path(path) as tmp:
        las.write(tmp, do_compress=path.suffix.lower() == ".laz")


def read_las(path: str | Path) -> PointCloud:
    """Read a LAS/LAZ file written by :func:`write_las` (other LAS files: normals are zero, views 0)."""
    import laspy

    try:
        las = laspy.read(str(path))
    except FileNotFoundError:
        raise InputError("file not found", path=str(path)) from None
    except (laspy.errors.LaspyException, ValueError) as e:
        raise InputError(f"not a readable LAS/LAZ file ({e})", path=str(path)) from None
    names = set(las.point_format.dimension_names)
    n = len(las.points)
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], 1)
    rgb = (np.stack([las.red, las.green, las.blue], 1) // 257).astype(np.uint8) if "red" in names \
        else np.zeros((n, 3), np.uint8)
    normal = np.stack([las.nx, las.ny, las.nz], 1) if "nx" in names else np.zeros((n, 3), np.float32)
    crs = las.header.parse_crs()
    return PointCloud(xyz, rgb, normal, np.asarray(las.user_data), np.asarray(las.point_source_id),
                      crs=crs.to_wkt() if crs is not None else "", classification=np.asarray(las.classification))


_PLY_FIELDS = [("x", "<f8", "double"), ("y", "<f8", "double"), ("z", "<f8", "double"),
               ("nx", "<f4", "float"), ("ny", "<f4", "float"), ("nz", "<f4", "float"),
               ("red", "u1", "uchar"), ("green", "u1", "uchar"), ("blue", "u1", "uchar"),
               ("view", "u1", "uchar"), ("master", "<u2", "ushort")]
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
              "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2",
              "int32": "<i4", "uint32": "<u4", "float32": "<f4", "float64": "<f8"}


def write_ply(path: str | Path, cloud: PointCloud) -> None:
    """Write ``cloud`` as binary little-endian PLY (atomically); masters and CRS go into comments."""
    arr = np.empty(len(cloud), dtype=[(n, t) for n, t, _ in _PLY_FIELDS])
    for i, c in enumerate("xyz"):
        arr[c] = cloud.xyz[:, i]
    for i, c in enumerate(("nx", "ny", "nz")):
        arr[c] = cloud.normal[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        arr[c] = cloud.rgb[:, i]
    arr["view"], arr["master"] = cloud.view, cloud.master
    lines = ["ply", "format binary_little_endian 1.0", "comment Oblique City dense points",
             f"comment views {' '.join(VIEWS)}"]
    lines += [f"comment master {i} {m}" for i, m in enumerate(cloud.masters)]
    if cloud.crs:
        lines.append("comment crs " + " ".join(cloud.crs.split()))
    lines.append(f"element vertex {len(cloud)}")
    lines += [f"property {t} {n}" for n, _, t in _PLY_FIELDS]
    lines.append("end_header")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(lines) + "\n").encode("ascii"))
        f.write(arr.tobytes())


def read_ply(path: str | Path) -> PointCloud:
    """Read a binary little-endian PLY vertex element (ours or any with x y z; other fields optional)."""
    path = str(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file", path=path, line=1)
    header = data[:end].decode("ascii", "replace").splitlines()
    fmt, n, dtype, masters, crs, in_vertex = None, 0, [], [], "", False
    for lineno, line in enumerate(header, 1):
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "comment" and len(tok) >= 4 and tok[1] == "master":
            masters.append(tok[3])
        elif tok[0] == "comment" and len(tok) >= 3 and tok[1] == "crs":
            crs = line.split("crs", 1)[1].strip()
        elif tok[0] == "element":
            in_vertex = tok[1] == "vertex"
            if in_vertex:
                n = int(tok[2])
        elif tok[0] == "property" and in_vertex:
            if tok[1] == "list" or tok[1] not in _PLY_TYPES:
                raise InputError(f"unsupported vertex property '{line}'", path=path, line=lineno, field="property")
            dtype.append((tok[2], _PLY_TYPES[tok[1]]))
    if fmt != "binary_little_endian":
        raise InputError(f"PLY format '{fmt}' not supported (binary_little_endian only)", path=path, line=2,
                         field="format")
    names = [d[0] for d in dtype]
    if not {"x", "y", "z"} <= set(names):
        raise InputError("PLY vertex has no x y z", path=path, field="property")
    arr = np.frombuffer(data, dtype=np.dtype(dtype), count=n, offset=end + len(b"end_header\n"))

    def cols(keys: tuple[str, ...], default_dtype) -> np.ndarray:
        if all(k in names for k in keys):
            return np.stack([arr[k] for k in keys], 1)
        return np.zeros((n, len(keys)), default_dtype)

    return PointCloud(cols(("x", "y", "z"), np.float64), cols(("red", "green", "blue"), np.uint8),
                      cols(("nx", "ny", "nz"), np.float32),
                      arr["view"] if "view" in names else np.zeros(n, np.uint8),
                      arr["master"] if "master" in names else np.zeros(n, np.uint16), masters, crs)
