"""Equirect <-> cube map in the OpenGL / WebGL GL_TEXTURE_CUBE_MAP convention.

Faces are stored [6, size, size, C] in the order +X, -X, +Y, -Y, +Z, -Z (GL's
TEXTURE_CUBE_MAP_POSITIVE_X + i, three.js CubeTexture px, nx, py, ny, pz, nz, Metal slices).
Row 0 of each face is the first row in memory (GL t = 0); columns run with s. A texel
(r, c) has s = (c + 1/2)/size, t = (r + 1/2)/size, sc = 2s - 1, tc = 2t - 1 and looks along

    face  direction (unnormalised)   image right (+col)  image down (+row)
    +X    ( 1,  -tc, -sc)            -z                  -y
    -X    (-1,  -tc,  sc)            +z                  -y
    +Y    ( sc,  1,   tc)            +x                  +z
    -Y    ( sc, -1,  -tc)            +x                  -z
    +Z    ( sc, -tc,  1)             +x                  -y
    -Z    (-sc, -tc, -1)             -x                  -y

(the face-selection table of the OpenGL spec, section "Cube Map Texture Selection").
This table is left-handed: seen from the cube's centre, every face image is mirrored
left-right relative to what a camera looking along the face axis would see (e.g. the -Z
face, which a default camera looks at, has +x on its LEFT). Consumers that want the
"as seen from inside" orientation must mirror; see docs/conventions.md for three.js and
Unity.
"""
from __future__ import annotations

import torch

from core.conventions import equirect_directions
from core.envmap import EnvmapError, check_envmap, resize_envmap, sample_envmap

CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


class CubemapError(ValueError):
    """Malformed cube map faces or size."""


def _check_size(size: int, name: str = "size") -> int:
    if isinstance(size, bool) or int(size) != size or int(size) < 1:
        raise CubemapError(f"{name} must be a positive integer, got {size!r}")
    return int(size)


def _face_direction(face: int, sc: torch.Tensor, tc: torch.Tensor) -> torch.Tensor:
    one = torch.ones_like(sc)
    table = {
        0: (one, -tc, -sc),
        1: (-one, -tc, sc),
        2: (sc, one, tc),
        3: (sc, -one, -tc),
        4: (sc, -tc, one),
        5: (-sc, -tc, -one),
    }
    return torch.stack(table[face], dim=-1)


def cubemap_directions(size: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Unit directions [6, size, size, 3] of every texel centre (faces in CUBE_FACES order)."""
    size = _check_size(size)
    centres = (torch.arange(size, dtype=torch.float64, device=device) + 0.5) / size * 2.0 - 1.0
    tc, sc = torch.meshgrid(centres, centres, indexing="ij")  # tc varies with row, sc with column
    d = torch.stack([_face_direction(f, sc, tc) for f in range(6)], dim=0)
    return (d / d.norm(dim=-1, keepdim=True)).to(dtype)


def equirect_to_cubemap(envmap: torch.Tensor, size: int) -> torch.Tensor:
    """Cube map faces [6, size, size, 3] from an equirect map.

    The map is first area-downsampled to height 2*size (about one equirect pixel per
    texel at the face centres), so small bright sources are not skipped, then sampled
    bilinearly at the texel centres.
    """
    h = check_envmap(envmap)
    size = _check_size(size)
    source = resize_envmap(envmap, 2 * size) if 2 * size < h else envmap
    d = cubemap_directions(size, device=envmap.device, dtype=torch.float64)
    return sample_envmap(source, d).to(envmap.dtype)


def direction_to_cube_texel(d: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Directions [..., 3] -> (face index, continuous row, continuous column) on size x size faces.

    Ties on the major axis go to x over y over z (any choice is a valid face edge).
    """
    x, y, z = d.unbind(-1)
    ax, ay, az = x.abs(), y.abs(), z.abs()
    use_x = (ax >= ay) & (ax >= az)
    use_y = ~use_x & (ay >= az)
    face = torch.where(
        use_x, torch.where(x >= 0, 0, 1), torch.where(use_y, torch.where(y >= 0, 2, 3), torch.where(z >= 0, 4, 5))
    )
    major = torch.where(use_x, ax, torch.where(use_y, ay, az)).clamp_min(torch.finfo(d.dtype).tiny)
    # invert the table in the module docstring
    sc = torch.stack((-z, z, x, x, x, -x), dim=-1).gather(-1, face[..., None])[..., 0] / major
    tc = torch.stack((-y, -y, z, -z, -y, -y), dim=-1).gather(-1, face[..., None])[..., 0] / major
    col = (sc + 1.0) * 0.5 * size - 0.5
    row = (tc + 1.0) * 0.5 * size - 0.5
    return face, row, col


def sample_cubemap(faces: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup in cube map faces [6, S, S, C] at directions [..., 3] -> [..., C].

    Interpolation clamps at face borders (within half a texel of an edge the value
    comes from the nearest border texels of the selected face).
    """
    size = _check_faces(faces)
    face, row, col = direction_to_cube_texel(d.to(torch.float64), size)
    row = row.clamp(0.0, size - 1.0)
    col = col.clamp(0.0, size - 1.0)
    r0 = torch.floor(row).clamp(max=max(size - 2, 0))
    c0 = torch.floor(col).clamp(max=max(size - 2, 0))
    tr = (row - r0)[..., None].to(faces.dtype)
    tcol = (col - c0)[..., None].to(faces.dtype)
    r0, c0 = r0.long(), c0.long()
    r1 = (r0 + 1).clamp(max=size - 1)
    c1 = (c0 + 1).clamp(max=size - 1)
    flat = faces.reshape(-1, faces.shape[-1])

    def at(r, c):
        return flat[(face * size + r) * size + c]

    top = at(r0, c0) * (1 - tcol) + at(r0, c1) * tcol
    bottom = at(r1, c0) * (1 - tcol) + at(r1, c1) * tcol
    return top * (1 - tr) + bottom * tr


def _check_faces(faces: torch.Tensor) -> int:
    if faces.ndim != 4 or faces.shape[0] != 6 or faces.shape[1] != faces.shape[2] or faces.shape[1] < 1:
        raise CubemapError(f"cube map faces must have shape [6, S, S, C], got {tuple(faces.shape)}")
    if not faces.is_floating_point():
        raise CubemapError(f"cube map faces must be floating point, got {faces.dtype}")
    return int(faces.shape[1])


def cubemap_to_equirect(faces: torch.Tensor, height: int) -> torch.Tensor:
    """Equirect map [height, 2 height, C] from cube map faces [6, S, S, C].

    When the target is coarser than the cube (height < 2 S) it is rendered at height 2 S
    and area-downsampled, so it integrates the faces rather than point-sampling them.
    """
    size = _check_faces(faces)
    if isinstance(height, bool) or int(height) != height or int(height) < 1:
        raise EnvmapError(f"height must be a positive integer, got {height!r}")
    height = int(height)
    work_height = max(height, 2 * size)
    d = equirect_directions(work_height, device=faces.device, dtype=torch.float64)
    out = sample_cubemap(faces, d)
    if work_height != height:
        if out.shape[-1] != 3:
            raise CubemapError("downsampling to a coarser equirect map needs 3 channels")
        out = resize_envmap(out, height)
    return out


__all__ = [
    "CUBE_FACES",
    "CubemapError",
    "cubemap_directions",
    "equirect_to_cubemap",
    "cubemap_to_equirect",
    "sample_cubemap",
    "direction_to_cube_texel",
]
