"""Sloan, Kautz & Snyder 2002, "Precomputed Radiance Transfer for Real-Time Rendering in Dynamic,
Low-Frequency Lighting Environments" — the SH PRT baseline. `method` registers `SHPRT` (name
"sh_prt"); `transfer` holds the precomputation; `study` its terms-vs-exponent row.
Kept import-free so that `import methods.sh_prt.<module>` stays light.
"""
