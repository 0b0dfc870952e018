"""Inverse diffusion: acquire kappa and mu of a block sample from measured radiance
(Wang et al. 2008, section 4 and appendix A)."""
