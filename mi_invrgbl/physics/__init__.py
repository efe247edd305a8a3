"""The shared physics under every layer: the one home of each formula.

The plugins (:mod:`mi_invrgbl.plugins`), the fit and the applications all
evaluate the same maths from here, so a renderer and its optimiser can never
disagree:

* :mod:`.brdf` - the paper's diffuse + Cook-Torrance reflectance;
* :mod:`.sh` - real spherical harmonics (numpy, matching ``dr.sh_eval``);
* :mod:`.hits` - detached traversal of Gaussians and differentiable blending;
* :mod:`.lighting` - per-Gaussian sky and sun light with traced visibility;
* :mod:`.gaussian_ply` - Gaussians in the 3DGS PLY convention.

Nothing here imports from the rest of the package.
"""
