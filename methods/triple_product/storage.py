"""Storage of global- vs local-frame parameterisation (Ma 2006 Tables 1–2, §3.2, §4.1).

The formulas; the table itself (the paper's settings as rows) is the study ``ma-tables``
(`methods.triple_product.study.storage_table`, ``python run_bench.py study ma-tables``).

Table 2 symbols (restored from the OCR-damaged text):
    n_L   sampling resolution of a lighting function (n^ω_L)
    r_L   number of precomputed rotations of the lighting
    n_V   sampling resolution of a visibility function
    n_x   number of vertices (visibility texels)
    n_o   number of sampled outgoing directions (n^ω_o)
    n_rho sampling resolution of a BRDF function (n^ω_ρ)
    r_rho number of precomputed rotations of normals (global frame: rotated BRDF copies)
    n_m   number of materials (n_ρ)

Table 1 storage (values, "without other parameterisation and data compression"):
    global frame:  n_L + n_x n_V + n_m r_rho n_o n_rho
    local frame:   r_L n_L + n_x n_V + n_m n_o n_rho
(the text: "(r_L − 1) n_L is less than (r_rho − 1) n_m n_o n_rho").

Paper numbers (§4.1): n_L = n_V = n_rho = 5120 (level-4 geodesic grid), r_L = 32·16 = 512 normals
(isotropic) or 32·16·32 = 16384 (normals × tangents, anisotropic), n_o = 8192 outgoing directions,
"excluding storage requirement for visibility" → 170 MB (isotropic), 480 MB (anisotropic) local vs
82 GB global (r_rho = 512). These reproduce EXACTLY with one material, one 4-byte float per value
(one channel) and MB = 2^20 bytes: 170 MiB = (512 + 8192)·5120·4 B; 480 MiB = (16384 + 8192)·5120·4 B;
the global 81 920 MiB = 80 GiB = 512·8192·5120·4 B (+ 0.02 MiB of lighting) is printed "82 GB", i.e.
the paper divided MiB by 1000 (80 GiB is 85.9 GB decimal). The OCR says "we sample 64 ω_o
-directions, i.e. n_o = 8192": 64 is not 8192; 8192 (e.g. 64 × 128) is what the totals need.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

MIB = 2 ** 20


@dataclass(frozen=True)
class StorageParams:
    """Table 2 symbols (module docstring); bytes_per_value: bytes per stored sample."""

    n_L: int = 5120
    r_L: int = 32 * 16
    n_V: int = 5120
    n_x: int = 0
    n_o: int = 8192
    n_rho: int = 5120
    r_rho: int = 32 * 16
    n_m: int = 1
    bytes_per_value: int = 4

    def __post_init__(self) -> None:
        for k, v in self.__dict__.items():
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{k} must be a non-negative int, got {v!r}")


# The paper's settings (§4.1), visibility excluded (n_x = 0) as in its 170/480 MB/82 GB numbers.
PAPER_ISOTROPIC = StorageParams()
PAPER_ANISOTROPIC = replace(PAPER_ISOTROPIC, r_L=32 * 16 * 32)


def global_frame_values(p: StorageParams) -> int:
    """Ma 2006 Table 1, global frame: n_L + n_x n_V + n_m r_rho n_o n_rho."""
    return p.n_L + p.n_x * p.n_V + p.n_m * p.r_rho * p.n_o * p.n_rho


def local_frame_values(p: StorageParams) -> int:
    """Ma 2006 Table 1, local frame: r_L n_L + n_x n_V + n_m n_o n_rho."""
    return p.r_L * p.n_L + p.n_x * p.n_V + p.n_m * p.n_o * p.n_rho


def storage_bytes(p: StorageParams) -> dict[str, int]:
    """{"global": bytes, "local": bytes} for the parameters."""
    return {"global": global_frame_values(p) * p.bytes_per_value,
            "local": local_frame_values(p) * p.bytes_per_value}
