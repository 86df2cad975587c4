"""Floor 1, the radiance field: the VM-decomposed tensorial grids whose lower scales are strided views of the
same tensors (``tensorial``), the field that evaluates density and appearance at every scale
(``radiance_field``), the density activation and a scale's density baked for rendering (``density``), its colour
MLP with the tiny-cuda-nn / torch choice (``color_mlp``), the space beyond an object's box (``outer_space``,
``far_background``), the grids' sizes for a voxel count and an upsampling schedule (``grid_sizes``), and the fused
kernels (NVIDIA Warp): their source (``fused_kernel_source``), the inference renderer's (``fused_kernels``) and a
training step's grid reads (``fused_training_reads``). Imports only the package root and other floor-1 rooms.
"""
