"""The machine model TOML format (DESIGN.md): read and validate, write."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.core.geometry import rpy_to_matrix
from mocap.core.machine import PRISMATIC, REVOLUTE, BucketAngle, Joint, Link, LinkSolid, Machine, Tolerance
from mocap.core.shapes import cylinder_triangles
from mocap.errors import InputError
from mocap.io import toml_writer
from mocap.io.atomic import write_text
from mocap.io.text import read_toml

MAX_LENGTH_M = 1e4  # 10 km: no machine's marker, joint origin or stroke lies farther
MACHINES_DIR = Path(__file__).resolve().parents[2] / "calibrations" / "machines"

_TOP_KEYS = {"name", "source", "links", "markers", "points", "bucket_angle", "tags", "tolerance"}
_LINK_KEYS = {"name", "parent", "joint", "box", "cylinder", "mesh"}
_BOX_KEYS = {"min", "max"}
_CYLINDER_KEYS = {"a", "b", "radius"}
_MESH_KEYS = {"file", "scale", "origin", "rpy_deg"}
_JOINT_KEYS = {"name", "type", "axis", "origin", "rpy_deg", "limits"}
_ITEM_KEYS = {"name", "link", "position"}
_MARKER_KEYS = _ITEM_KEYS | {"tag", "normal"}
_TAGS_KEYS = {"dictionary"}
DEFAULT_TAG_DICTIONARY = "DICT_4X4_50"
_BUCKET_KEYS = {"link", "direction"}


def resolve_machine_path(name_or_path: str) -> Path:
    """A machine TOML path, or the name of one shipped in calibrations/machines/."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        return path
    shipped = MACHINES_DIR / f"{name_or_path}.toml"
    if shipped.exists():
        return shipped
    known = ", ".join(sorted(p.stem for p in MACHINES_DIR.glob("*.toml")))
    raise InputError(
        f"no machine model named {name_or_path!r}; give a TOML path or one of: {known}",
        path=name_or_path,
    )


def load_machine(name_or_path: str | Path) -> Machine:
    """Read and validate a machine model; raises InputError naming the file and entry."""
    path = resolve_machine_path(str(name_or_path))
    data = read_toml(path, "check the machine model path")
    return machine_from_dict(data, path)


def machine_from_dict(data: dict, path: str | Path = "<machine>") -> Machine:
    """Validate a parsed machine TOML document and build the model."""
    _check_keys(data, _TOP_KEYS, path, "top level")
    name = _string(data, "name", path, "top level")
    source = data.get("source", "")
    raw_links = data.get("links")
    if not isinstance(raw_links, list) or not raw_links:
        raise InputError("no [[links]]: a machine needs at least its base link", path=path)
    links = _links(raw_links, path)
    boxes = _boxes(raw_links, links, path)
    solids = _solids(raw_links, links, path)
    link_index = {link.name: i for i, link in enumerate(links)}

    markers = _items(data.get("markers", []), "markers", link_index, path, _MARKER_KEYS)
    if not markers[0]:
        raise InputError("no [[markers]]: calibration needs markers on the links", path=path)
    points = _items(data.get("points", []), "points", link_index, path, _ITEM_KEYS)
    names = markers[0] + points[0]
    _no_duplicates(names, path, "markers and points")

    bucket = None
    if "bucket_angle" in data:
        raw = data["bucket_angle"]
        where = "[bucket_angle]"
        if not isinstance(raw, dict):
            raise InputError("must be a table with link and direction", path=path, where=where)
        _check_keys(raw, _BUCKET_KEYS, path, where)
        link = _string(raw, "link", path, where)
        if link not in link_index:
            raise InputError(f"unknown link {link!r}", path=path, where=where)
        direction = _unit(_vector(raw, "direction", path, where), path, where, "direction")
        bucket = BucketAngle(link_index[link], direction)

    tags, dictionary = _tags(data, markers[3], path)
    tolerance = None
    if "tolerance" in data:
        try:
            tolerance = Tolerance.parse(data["tolerance"])
        except (TypeError, ValueError):
            raise InputError(
                f"tolerance {data['tolerance']!r} must be a fraction (0.05, \"5%\") or a length (\"0.03 m\", "
                "\"3 cm\"): how far the measured marker positions may be off",
                path=path, where="top level",
            ) from None
    return Machine(
        name=name,
        source=str(source),
        links=tuple(links),
        marker_names=tuple(markers[0]),
        marker_links=np.array(markers[1], dtype=int),
        marker_positions=np.array(markers[2], dtype=float).reshape(-1, 3),
        point_names=tuple(points[0]),
        point_links=np.array(points[1], dtype=int),
        point_positions=np.array(points[2], dtype=float).reshape(-1, 3),
        bucket_angle=bucket,
        marker_tags=tags,
        tag_dictionary=dictionary,
        tolerance=tolerance,
        marker_normals=np.array(markers[4]).reshape(-1, 3) if np.any(np.isfinite(markers[4])) else None,
        link_boxes=boxes,
        link_solids=solids,
    )


def _boxes(raw_links: list, links: list[Link], path) -> np.ndarray | None:
    """(L, 2, 3) the links' stated boxes `box = {min = [x, y, z], max = [x, y, z]}` (metres, the
    link's frame), in the order of `links` (NaN rows: not stated); None if no link states one."""
    order = {link.name: i for i, link in enumerate(links)}
    boxes = np.full((len(links), 2, 3), np.nan)
    for raw in raw_links:
        if "box" not in raw:
            continue
        where = f"link {raw['name']!r} box"
        box = raw["box"]
        if not isinstance(box, dict):
            raise InputError("box must be an inline table {min = [x, y, z], max = [x, y, z]} (metres, the link's "
                             "frame)", path=path, where=where)
        _check_keys(box, _BOX_KEYS, path, where)
        low = _length(_vector(box, "min", path, where), path, where, "min")
        high = _length(_vector(box, "max", path, where), path, where, "max")
        if not np.all(low < high):
            raise InputError(f"min {low.tolist()} must be below max {high.tolist()} on every axis", path=path,
                             where=where)
        boxes[order[raw["name"]]] = low, high
    return boxes if np.any(np.isfinite(boxes)) else None


def _solids(raw_links: list, links: list[Link], path) -> tuple[LinkSolid, ...]:
    """The links' stated cylinders `cylinder = {a = [x, y, z], b = [x, y, z], radius = r}` and
    meshes `mesh = {file = "boom.stl", scale = s, origin = [x, y, z], rpy_deg = [r, p, y]}`
    (each a table or an array of tables; metres, the link's frame; a mesh file's path relative
    to the model file's folder, its vertices scaled, turned by rpy_deg and moved by origin
    as a URDF's visual origin), in link order."""
    order = {link.name: i for i, link in enumerate(links)}
    solids = []
    for raw in raw_links:
        for kind, keys, read in (("cylinder", _CYLINDER_KEYS, _cylinder), ("mesh", _MESH_KEYS, _mesh)):
            entries = raw.get(kind, [])
            entries = [entries] if isinstance(entries, dict) else entries
            if not isinstance(entries, list):
                raise InputError(f"{kind} must be an inline table or an array of them (see docs/formats.md)",
                                 path=path, where=f"link {raw['name']!r} {kind}")
            for k, entry in enumerate(entries):
                where = f"link {raw['name']!r} {kind}" + (f"[{k}]" if len(entries) > 1 else "")
                if not isinstance(entry, dict):
                    raise InputError(f"{kind} must be an inline table (see docs/formats.md)", path=path, where=where)
                _check_keys(entry, keys, path, where)
                triangles, source = read(entry, path, where)
                solids.append(LinkSolid(order[raw["name"]], kind, triangles, source))
    return tuple(sorted(solids, key=lambda s: s.link))


def _cylinder(raw: dict, path, where) -> tuple[np.ndarray, dict]:
    a = _length(_vector(raw, "a", path, where), path, where, "a")
    b = _length(_vector(raw, "b", path, where), path, where, "b")
    radius = raw.get("radius")
    if not isinstance(radius, (int, float)) or isinstance(radius, bool) or not 0 < radius <= MAX_LENGTH_M:
        raise InputError(f"radius {radius!r} must be a number of metres above 0", path=path, where=where)
    if np.linalg.norm(b - a) <= 0:
        raise InputError(f"a and b are the same point {a.tolist()}: give the two ends of the cylinder's axis",
                         path=path, where=where)
    return cylinder_triangles(a, b, float(radius)), {"a": a.tolist(), "b": b.tolist(), "radius": float(radius)}


def _mesh(raw: dict, path, where) -> tuple[np.ndarray, dict]:
    name = _string(raw, "file", path, where)
    file = Path(name)
    if not file.is_absolute() and Path(path).is_file():
        file = Path(path).parent / file
    if not file.is_file():
        raise InputError(f"mesh file {str(file)!r} not found: give its path relative to the model file's folder",
                         path=path, where=where)
    scale = raw.get("scale", 1.0)
    scale = [scale] * 3 if isinstance(scale, (int, float)) and not isinstance(scale, bool) else scale
    scale = np.asarray(_numbers(scale, 3, path, where, "scale"))
    if not np.all(scale > 0):
        raise InputError(f"scale {scale.tolist()} must be above 0 (a number, or 3 numbers)", path=path, where=where)
    origin = _length(_vector(raw, "origin", path, where, default=[0, 0, 0]), path, where, "origin")
    rpy_deg = _vector(raw, "rpy_deg", path, where, default=[0, 0, 0])
    triangles = _mesh_triangles(file, path, where) * scale
    triangles = triangles @ rpy_to_matrix(np.radians(rpy_deg)).T + origin
    if np.any(np.abs(triangles) > MAX_LENGTH_M):
        raise InputError(f"mesh {str(file)!r} reaches beyond {MAX_LENGTH_M:g} m: give its scale to metres",
                         path=path, where=where)
    if np.prod(scale) < 0:  # a mirroring scale turns the winding inside out
        triangles = triangles[:, ::-1]
    source = {"file": str(file.resolve()), "scale": scale.tolist(), "origin": origin.tolist(),
              "rpy_deg": rpy_deg.tolist()}
    return np.ascontiguousarray(triangles), source


def _mesh_triangles(file: Path, path, where) -> np.ndarray:
    """(T, 3, 3) a mesh file's triangles (STL, OBJ, PLY, DAE, ... as `trimesh` reads them),
    wound outward where the surface is closed."""
    import trimesh

    try:
        mesh = trimesh.load(file, force="mesh")
    except Exception as exc:  # the reader's own message names what is wrong
        raise InputError(f"mesh file {str(file)!r} cannot be read ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}): "
                         "give an STL, OBJ, PLY or DAE file", path=path, where=where) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"mesh file {str(file)!r} holds no triangles: give a surface mesh", path=path, where=where)
    if mesh.is_watertight:
        trimesh.repair.fix_normals(mesh)
    return np.asarray(mesh.vertices, dtype=float)[np.asarray(mesh.faces)]


def _tags(data: dict, tags: list, path) -> tuple[np.ndarray | None, str | None]:
    """The markers' tag ids (None if no marker carries one) and the [tags] dictionary."""
    raw = data.get("tags")
    if raw is not None:
        if not isinstance(raw, dict):
            raise InputError("[tags] must be a table with the tag dictionary", path=path, where="[tags]")
        _check_keys(raw, _TAGS_KEYS, path, "[tags]")
    if all(t < 0 for t in tags):
        return None, None
    from mocap.core.tags import tag_dictionary  # OpenCV's, only for a machine with tags

    dictionary = str((raw or {}).get("dictionary", DEFAULT_TAG_DICTIONARY))
    try:
        size = tag_dictionary(dictionary).bytesList.shape[0]
    except ValueError as exc:
        raise InputError(str(exc), path=path, where="[tags] dictionary") from None
    seen: dict[int, int] = {}
    for k, t in enumerate(tags):
        if t < 0:
            continue
        if t >= size:
            raise InputError(f"tag {t} is not in {dictionary} (ids 0 to {size - 1})", path=path, where=f"markers[{k}]")
        if t in seen:
            raise InputError(f"tag {t} is on markers[{seen[t]}] too: each tag id marks one marker", path=path,
                             where=f"markers[{k}]")
        seen[t] = k
    return np.array(tags, dtype=int), dictionary


def _links(raw_links: list, path) -> list[Link]:
    """Links in topological order (base first), validated."""
    entries = []
    for k, raw in enumerate(raw_links):
        where = f"links[{k}]"
        if not isinstance(raw, dict):
            raise InputError("each [[links]] entry must be a table", path=path, where=where)
        _check_keys(raw, _LINK_KEYS, path, where)
        name = _string(raw, "name", path, where)
        where = f"link {name!r}"
        if k == 0:
            if "parent" in raw or "joint" in raw:
                raise InputError(
                    "the first link is the base: it has no parent and no joint; put the "
                    "base link first",
                    path=path,
                    where=where,
                )
            entries.append((name, None, None))
            continue
        if "parent" not in raw:
            raise InputError(
                "no parent: only the first link (the base) has none", path=path, where=where
            )
        if "joint" not in raw:
            raise InputError("no joint: every link but the base needs one", path=path, where=where)
        entries.append((name, _string(raw, "parent", path, where), _joint(raw["joint"], path, where)))
    _no_duplicates([e[0] for e in entries], path, "links")
    _no_duplicates([e[2].name for e in entries[1:]], path, "joints")
    names = {e[0] for e in entries}
    for name, parent, _ in entries[1:]:
        if parent not in names:
            raise InputError(f"unknown parent {parent!r}", path=path, where=f"link {name!r}")

    placed = {entries[0][0]: 0}
    links = [Link(entries[0][0], None, None)]
    pending = entries[1:]
    while pending:
        ready = [e for e in pending if e[1] in placed]
        if not ready:
            cycle = ", ".join(repr(e[0]) for e in pending)
            raise InputError(
                f"links {cycle} form a cycle and never reach the base", path=path, where="links"
            )
        for name, parent, joint in ready:
            placed[name] = len(links)
            links.append(Link(name, placed[parent], joint))
        pending = [e for e in pending if e[0] not in placed]
    return links


def _joint(raw, path, where) -> Joint:
    where = f"{where} joint"
    if not isinstance(raw, dict):
        raise InputError("joint must be an inline table", path=path, where=where)
    _check_keys(raw, _JOINT_KEYS, path, where)
    name = _string(raw, "name", path, where)
    kind = _string(raw, "type", path, where)
    if kind not in (REVOLUTE, PRISMATIC):
        raise InputError(
            f"type {kind!r} is not 'revolute' or 'prismatic'", path=path, where=f"{where} {name!r}"
        )
    where = f"{where} {name!r}"
    axis = _unit(_vector(raw, "axis", path, where), path, where, "axis")
    origin = _length(_vector(raw, "origin", path, where, default=[0, 0, 0]), path, where, "origin")
    rpy = np.radians(_vector(raw, "rpy_deg", path, where, default=[0, 0, 0]))
    if "limits" in raw:
        limits = np.asarray(_numbers(raw["limits"], 2, path, where, "limits"))
        if not limits[0] < limits[1]:
            raise InputError(
                f"limits {limits.tolist()} must be [lower, upper] with lower < upper",
                path=path,
                where=where,
            )
        if kind == PRISMATIC and np.any(np.abs(limits) > MAX_LENGTH_M):
            raise InputError(
                f"prismatic limits {limits.tolist()} reach beyond {MAX_LENGTH_M:g} m: give the joint's "
                "stroke in metres",
                path=path,
                where=where,
            )
        if kind == REVOLUTE:
            if np.any(np.abs(limits) > 360):
                raise InputError(
                    f"revolute limits {limits.tolist()} exceed ±360: they are degrees",
                    path=path,
                    where=where,
                )
            limits = np.radians(limits)
    else:
        limits = np.array([-np.pi, np.pi]) if kind == REVOLUTE else np.array([-np.inf, np.inf])
    return Joint(name, kind, axis, origin, rpy, limits)


def _items(raw_items, section, link_index, path, keys):
    """Named points on links: names, link indices, positions, tag ids (-1: none) and the
    markers' stated normals (unit, link frame; NaN: not stated)."""
    names, links, positions, tags, normals = [], [], [], [], []
    if not isinstance(raw_items, list):
        raise InputError(f"{section} must be an array of tables [[{section}]]", path=path)
    for k, raw in enumerate(raw_items):
        where = f"{section}[{k}]"
        if not isinstance(raw, dict):
            raise InputError("must be a table", path=path, where=where)
        _check_keys(raw, keys, path, where)
        name = _string(raw, "name", path, where)
        where = f"{section[:-1]} {name!r}"
        link = _string(raw, "link", path, where)
        if link not in link_index:
            raise InputError(f"unknown link {link!r}", path=path, where=where)
        tag = raw.get("tag", -1)
        if "tag" in raw and (isinstance(tag, bool) or not isinstance(tag, int) or tag < 0):
            raise InputError(f"tag {tag!r} must be a whole number >= 0 (the tag's id)", path=path, where=where)
        names.append(name)
        links.append(link_index[link])
        positions.append(_length(_vector(raw, "position", path, where), path, where, "position"))
        tags.append(tag)
        normals.append(_unit(_vector(raw, "normal", path, where), path, where, "normal") if "normal" in raw
                       else np.full(3, np.nan))
    return names, links, positions, tags, normals


def _check_keys(raw: dict, allowed: set, path, where) -> None:
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise InputError(
            f"unknown key(s) {', '.join(map(repr, unknown))}; allowed: {', '.join(sorted(allowed))}",
            path=path,
            where=where,
        )


def _string(raw: dict, key: str, path, where) -> str:
    value = raw.get(key)
    if not isinstance(value, str) or not value:
        raise InputError(f"{key!r} must be a non-empty string", path=path, where=where)
    return value


def _numbers(value, n, path, where, key) -> list[float]:
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        raise InputError(f"{key!r} must be a list of {n} numbers, got {value!r}", path=path, where=where)
    if not all(np.isfinite(value)):
        raise InputError(f"{key!r} must be finite, got {value!r}", path=path, where=where)
    return [float(v) for v in value]


def _vector(raw: dict, key: str, path, where, default=None) -> np.ndarray:
    if key not in raw:
        if default is None:
            raise InputError(f"missing {key!r} (3 numbers, metres)", path=path, where=where)
        return np.asarray(default, dtype=float)
    return np.asarray(_numbers(raw[key], 3, path, where, key))


def _length(vector: np.ndarray, path, where, key) -> np.ndarray:
    """A position in metres, refused beyond MAX_LENGTH_M (a unit slip, a corrupt number)."""
    if np.any(np.abs(vector) > MAX_LENGTH_M):
        raise InputError(f"{key!r} {vector.tolist()} lies beyond {MAX_LENGTH_M:g} m: "
                         "give it in metres", path=path, where=where)
    return vector


def _unit(vector: np.ndarray, path, where, key) -> np.ndarray:
    norm = np.linalg.norm(vector)
    if norm < 1e-9:
        raise InputError(f"{key!r} is a zero vector; give a direction", path=path, where=where)
    return vector / norm


def _no_duplicates(names: list[str], path, what: str) -> None:
    seen = set()
    for name in names:
        if name in seen:
            raise InputError(f"duplicate name {name!r} among {what}", path=path)
        seen.add(name)


def machine_to_dict(machine: Machine) -> dict:
    """The TOML document of a machine model (inverse of `machine_from_dict`)."""
    links = []
    for link in machine.links:
        entry = {"name": link.name}
        if link.joint is not None:
            joint = link.joint
            limits = joint.limits if joint.type == PRISMATIC else np.degrees(joint.limits)
            entry["parent"] = machine.links[link.parent].name
            entry["joint"] = {
                "name": joint.name,
                "type": joint.type,
                "axis": joint.axis.tolist(),
                "origin": joint.origin.tolist(),
                "rpy_deg": np.degrees(joint.rpy).tolist(),
            }
            if np.all(np.isfinite(limits)):
                entry["joint"]["limits"] = np.asarray(limits).tolist()
        box = None if machine.link_boxes is None else machine.link_boxes[len(links)]
        if box is not None and np.all(np.isfinite(box)):
            entry["box"] = {"min": box[0].tolist(), "max": box[1].tolist()}
        for kind in ("cylinder", "mesh"):
            stated = [dict(s.source) for s in machine.link_solids if s.link == len(links) and s.kind == kind]
            if stated:
                entry[kind] = stated[0] if len(stated) == 1 else stated
        links.append(entry)

    def items(names, link_ids, positions, tags=None, normals=None):
        out = [
            {"name": n, "link": machine.links[l].name, "position": p.tolist()}
            for n, l, p in zip(names, link_ids, positions)
        ]
        for entry, tag in zip(out, tags if tags is not None else []):
            if tag >= 0:
                entry["tag"] = int(tag)
        for entry, normal in zip(out, normals if normals is not None else []):
            if np.all(np.isfinite(normal)):
                entry["normal"] = normal.tolist()
        return out

    data = {"name": machine.name, "source": machine.source, "links": links}
    if machine.tolerance:
        data["tolerance"] = str(machine.tolerance) if machine.tolerance.metres else machine.tolerance.fraction
    if machine.tag_dictionary is not None and np.any(machine.tags >= 0):
        data["tags"] = {"dictionary": machine.tag_dictionary}
    data["markers"] = items(machine.marker_names, machine.marker_links, machine.marker_positions, machine.tags,
                            machine.marker_normals)
    if machine.point_names:
        data["points"] = items(machine.point_names, machine.point_links, machine.point_positions)
    if machine.bucket_angle is not None:
        data["bucket_angle"] = {
            "link": machine.links[machine.bucket_angle.link].name,
            "direction": machine.bucket_angle.direction.tolist(),
        }
    return data


def save_machine(machine: Machine, path: str | Path) -> None:
    write_text(path, toml_writer.dumps(machine_to_dict(machine)))
