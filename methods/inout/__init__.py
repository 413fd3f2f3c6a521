"""In-out BRDF factorization (Mahajan, Tseng & Ramamoorthi 2008).

``methods.inout.analysis`` — the BRDF-matrix SVD analysis and the rules for the number of terms K.
(Nothing heavy is imported here; the renderer lives in its own module.)
"""

from methods.inout.method import InOut  # noqa: E402,F401  (registers "inout")
