"""Sun et al. 2007, "Interactive Relighting with Dynamic BRDFs" (precomputed transfer tensors).

BRDF side: `brdf_space` (§4.2 navigation), `lobes` (§4.1 specular lobe separation),
`brdf_tensor` (§3.2 eq. 2 Tucker BRDF tensor, Fig. 5), `pca` (§4.3 PCA basis of the PTTs).
Kept import-free so that `import methods.ptt.<module>` stays light.
"""
