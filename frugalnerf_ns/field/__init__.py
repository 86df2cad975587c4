"""Floor 1, the radiance field: the VM-decomposed tensorial grids whose lower scales are strided views of the
same tensors (``tensorial``), the field that evaluates density and appearance at every scale
(``radiance_field``) and its colour MLP with the tiny-cuda-nn / torch choice (``color_mlp``). Imports only the
package root and other floor-1 rooms.
"""
