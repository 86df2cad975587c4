"""FrugalNeRF's model settings (``--pipeline.model.*``): one field per setting, each with its meaning.
Defaults are the paper's LLFF 2-view settings; presets (``configs/presets.yaml``) override them.

The settings know nothing of the model class: ``model/frugalnerf.py`` binds them to the model as
``FrugalNeRFModelConfig`` (its ``_target``), so the modules that read settings (objective, schedule) import
this one and no import runs in a circle."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Literal, Optional, Tuple

import tyro
from nerfstudio.configs.config_utils import to_immutable_dict
from nerfstudio.models.base_model import ModelConfig

from frugalnerf_ns.field.color_mlp import MLPImplementation
from frugalnerf_ns.field.density import DensityActivation


Background = Literal["random_white", "white", "black"]


@dataclass
class FrugalNeRFSettings(ModelConfig):
    """FrugalNeRF model settings; defaults are the paper's LLFF 2-view settings."""

    enable_collider: bool = False
    """Rays are clipped to the scene box by the model itself, so nerfstudio's near/far collider is off."""
    # Inherited from nerfstudio's ModelConfig and read by no part of this model: left out of --help (tyro's
    # Suppress), with nerfstudio's defaults, so that config.yml files that hold them still load. (The collider that
    # enable_collider would build from collider_params sets near/far bounds the model never reads.)
    collider_params: tyro.conf.Suppress[Optional[Dict[str, float]]] = to_immutable_dict({"near_plane": 2.0, "far_plane": 6.0})
    """nerfstudio's near/far collider bounds; unread (the model clips rays to its box)."""
    loss_coefficients: tyro.conf.Suppress[Dict[str, float]] = to_immutable_dict({"rgb_loss_coarse": 1.0, "rgb_loss_fine": 1.0})
    """nerfstudio's coarse/fine colour-loss weights; unread (the loss weights are this config's ``*_weight`` fields)."""
    prompt: tyro.conf.Suppress[Optional[str]] = None
    """nerfstudio's text prompt for text-to-NeRF models; unread."""
    near_plane: float = 0.05
    """Samples closer to the camera than this are skipped."""
    initial_voxels: int = 64**3
    """Voxel count of the grid at the start of training."""
    final_voxels: int = 640**3
    """Voxel count after the last upsampling (paper: 640^3 for LLFF, 300^3 for DTU); ignored with auto-grid."""
    auto_grid: bool = False
    """Size the final grid from the training pixels instead of final-voxels: side = 0.52 sqrt(pixels), the
    paper's ratio (640^3 for two 1008x756 views; ~320^3 for two 504x378 views), clamped to 32..640."""
    upsample_at: Tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
    """When the grid is upsampled (log-linear in voxel count), as fractions of the schedule (--schedule-steps,
    by default the run's iterations: the paper's steps 500, 1000, ..., 3000 of 5000); the grid optimiser
    restarts."""
    alpha_mask_at: Tuple[float, ...] = (0.2, 0.4)
    """When the occupancy (alpha) mask is recomputed, as fractions of the schedule (paper: steps 1000 and 2000
    of 5000); the box shrinks to it the first time."""
    alpha_mask_threshold: float = 1e-4
    """Alpha below which a (dilated) voxel counts as empty."""
    density_components: Tuple[int, int, int] = (16, 4, 4)
    """Components of the XY, XZ, YZ density planes and their lines."""
    appearance_components: Tuple[int, int, int] = (48, 12, 12)
    """Components of the XY, XZ, YZ appearance planes and their lines."""
    appearance_dim: int = 27
    """Output size of the appearance basis matrix shared by all scales."""
    num_lower_scales: int = 2
    """L: lower scales below the full one (2 = three scales)."""
    downsample_ratio: int = 4
    """Stride ratio between consecutive scales."""
    scale_spanning_grid: bool = False
    """Give every axis of the grid (at the start, after each upsampling and after the shrink) a multiple of the
    coarsest stride plus one entries (16k+1 with ratio 4 and two lower scales), so each lower scale's strided
    view spans the whole box. Off: the views stop short of the box's far faces (at a 176-entry axis the 1/16
    scale's last entry sits at 91 % of it) and the rest of the axis reads that entry."""
    training_density_read: Literal["nodes", "planes"] = "nodes"
    """How a training step reads density: "nodes", every plane times its line summed on the grid's nodes once
    per step and read trilinearly at every scale (``FrugalNeRFField.shared_density_nodes``; grids above 256^3
    nodes read the planes, where that is faster; on the CPU grids from 2^23 nodes read them with the fused kernels
    where they compile, ``kernels``); "planes", the planes and lines at every sample (the reference; same values
    and gradients to float rounding)."""
    step_ratio: float = 0.5
    """Sample step at full resolution, in voxels."""
    max_samples_per_ray: int = 1024
    """Upper bound on samples per ray at the full scale."""
    distance_scale: float = 25.0
    """Sample distances are multiplied by this before alpha compositing (TensoRF)."""
    density_activation: DensityActivation = "relu"
    """relu for forward-facing scenes, softplus (shifted by -10) for object scenes."""
    weight_threshold: float = 1e-4
    """Colour is evaluated only at samples whose compositing weight exceeds this."""
    fast_inference: bool = True
    """Outside training, without gradients, march in blocks and stop each ray once its transmittance is below
    1e-4 (model/rendering.py, ``render_scale_inference``); False renders with the training marcher."""
    kernels: Literal["auto", "warp", "torch"] = "auto"
    """Fused kernels (NVIDIA Warp, compiled at first use) for rendering without gradients on the CPU: the density
    march, the appearance reads of a grid too large to bake and the space beyond the box; and in training on the
    CPU, the density and appearance reads of a large grid's planes and lines with their backward (from 2^23 nodes;
    the density in place of ``training_density_read``'s nodes). torch: the reference path. auto: Warp where it
    imports and compiles, else torch with one line."""
    mlp_hidden_dim: int = 128
    """Width of the colour MLP."""
    feature_pe: int = 0
    """Positional-encoding frequencies of the appearance features fed to the MLP (0: none)."""
    use_view_dirs: bool = False
    """Feed the viewing direction to the colour MLP."""
    view_pe: int = 0
    """Positional-encoding frequencies of the viewing direction (0: none)."""
    mlp_implementation: MLPImplementation = "auto"
    """auto: tinycudann when importable with CUDA, torch otherwise."""
    eval_all_scales: bool = False
    """Outside training and the viewer (ns-eval, evaluation during training, ns-render), render every scale and
    score the lower ones too (per-scale PSNR, depth and accumulation images). Off: only the full scale, the one
    the metrics and videos use (1.3x faster on fern, docs/notes/video.md). For a trained run, set
    ``eval_all_scales: true`` in its config.yml."""
    background: Background = "random_white"
    """Training background: white or black at random per batch (reference code), or fixed."""
    far_background: bool = True
    """Where the dataparser's box holds only the near part of an unbounded scene (an LLFF-layout capture whose
    cameras converge on an object in a room; metadata ``far_background``), learn a colour per viewing direction
    for the rays leaving it instead of ``background``. Other scenes never have one."""
    far_background_resolution: Tuple[int, int] = (32, 64)
    """Rows and columns (latitude x longitude) of the far background's map; coarse, so that it holds the far
    room's broad colours and not the object's detail."""
    outer_space_resolution: int = 128
    """With a far background: nodes per axis of the VM grids that hold the space beyond the box (the room around
    a captured object) in contracted coordinates (``field/outer_space.py``); the direction map stays behind them,
    at infinity. 0: the direction map alone (on the sphere of the sparse points beyond the box)."""
    outer_space_samples: int = 32
    """Samples per ray beyond the box, linear in disparity."""
    outer_space_front_samples: int = 16
    """Samples per ray between a camera outside the box and the box, evenly in distance (0: that space is empty)."""
    outer_distortion_weight: float = 0.01
    """mip-NeRF 360's distortion loss on the samples outside the box (its weight, 0.01), in front of and behind it:
    a ray's weight there in one place, not spread as fog or floaters in front of the cameras."""
    full_scale_color_weight: float = 1.0
    """Eq. 1 weight of the full-resolution colour loss."""
    lower_scale_color_weight: float = 10.0
    """Eq. 1 weight of each lower scale's colour loss (LLFF 10, DTU and RealEstate 1)."""
    appearance_tv_weight: float = 10.0
    """TV on the appearance grid."""
    density_tv_weight: float = 10.0
    """Edge-aware TV on the density grid (weights exp(-|grad appearance|))."""
    tv_plane_weight: float = 1e-2
    """Weight of the planes inside a TV term."""
    tv_line_weight: float = 1e-4
    """Weight of the lines inside a TV term."""
    density_l1_weight: float = 0.0
    """L1 sparsity on the density components."""
    distortion_weight: float = 5e-4
    """Mip-NeRF 360 distortion loss."""
    geo_weight: float = 0.01
    """lambda_geo of the cross-scale geometric adaptation loss (Eq. 10-11); 0 turns it off."""
    geo_novel_weight: Optional[float] = None
    """lambda_geo of the novel-view rays' term (Eq. 10's second summand) where it differs from the training
    patches' (geo_weight); None: geo_weight for both, as the paper. Not a paper setting: the paper credits the novel
    rays' term with suppressing floaters where no training view looks (Sec. 3.5, "Novel View Regularizations"); at
    the CPU preset the two summands act on different scenes, and frugalnerf-cpu weighs the novel rays' 0.01 against
    the training patches' 0.1 (docs/notes/benchmarks.md, "The other split")."""
    reprojection_threshold: float = 0.5
    """Rays whose least reprojection error over the scales exceeds this are left out of L_geo (paper: 0.5;
    in colour units for rmse, i.e. the warped patch is off by half the colour range)."""
    photometric_weight: float = 0.0
    """Not a paper setting (0: off, every preset): weight of a photometric consistency term on the training
    patches (``losses.photometric_consistency_loss``): each pixel carried at the full scale's rendered depth into
    its nearest other training view should land on its own colour, with gradient through the depth. Compared at
    the images' size and at each coarser level of ``photometric_levels`` (2x blocks each) so a depth a few pixels
    off still sees a slope."""
    photometric_levels: int = 3
    """Image sizes the photometric term compares at: full, then 2x, 4x, ... averaged blocks."""
    photometric_max_error: float = 0.2
    """Patches whose warp at the coarsest level is off by more than this RMSE (colour units, Eq. 2's measure) or
    leaves the other image are left out: occluded or unseen there, no depth explains them."""
    depth_smoothness_weight: float = 5e-3
    """Depth smoothness on novel-view 2x2 patches (LLFF 5e-3, DTU 50, RealEstate 0); lower scales / 16, 256."""
    occlusion_weight: float = 0.0
    """Occlusion regulariser (FreeNeRF): density of the first samples of every ray, for object scenes on a
    black or white background; off (0) for forward-facing scenes and, in the reference, at 2 views."""
    occlusion_near_samples: int = 10
    """Samples nearest the camera (full scale; lower scales use proportionally fewer) the occlusion loss
    always penalises."""
    occlusion_background_samples: int = 15
    """Samples nearest the camera in which black or white samples are also penalised (background prior)."""
    occlusion_background_prior: bool = True
    """Penalise near samples whose colour is black or white (the background of DTU-like object scenes)."""
    sparse_depth_weight: float = 0.5
    """lambda_sd: MSE between inverse rendered and inverse sparse-point depth (metric), at every scale
    (LLFF / DTU 0.5, RealEstate 0.05); points come from the datamanager (--pipeline.datamanager.sparse-depth)."""
    sparse_depth_error: Literal["auto", "inverse", "relative"] = "inverse"
    """How L_sd measures a point's depth error: "inverse", Eq. 11's MSE of inverse depths (the paper); "relative",
    the inverse-depth difference over the point's own inverse depth under a Huber penalty
    (``losses.relative_disparity_loss``), so that far points pull as hard as near ones; "auto", relative where the
    scene is an object in a metric box with the room beyond it (a far background: phone captures), inverse
    elsewhere (LLFF in NDC, DTU, Blender: the paper's protocols)."""
    mono_depth_weight: float = 0.01
    """lambda_d of the optional monocular depth loss (1 - Pearson correlation of rendered and predicted depth,
    every scale); active only with --pipeline.datamanager.mono-depth-model."""
    loss_weight_decay: float = 0.025
    """Over the run the lower-scale colour, TV, occlusion, depth-smoothness, sparse and monocular depth weights
    fall by this factor and the distortion weight grows by it (reference schedule, the learning rate's decay:
    LLFF 0.025, DTU 0.05); 1 keeps every weight constant."""

    carve_unseen: Literal["auto", "on", "off"] = "auto"
    """In a metric box, whether the alpha mask (``alpha_mask_at``) also empties the space no training camera sees
    (``objective.carve_unseen_space``). No photo's colour reaches it; in the plain-fit regime (``room_warp_losses``)
    no novel ray's L_geo does either, and the grid's initial density stays there as fog: a test camera between two
    photos can sit inside it and render one grey colour (the juice box's 40-degree split, 3 of 6 test views; over 2
    seeds the wide split 15.42 -> 16.07 dB, the 40-degree split 12.32 -> 12.56: docs/notes/captures.md, "Two
    regimes"). "auto": where the split is fitted plainly; "on": every metric box; "off": never. NDC boxes are the
    training frusta."""
    room_warp_losses: Literal["auto", "on", "off"] = "auto"
    """Where the scene is an object in a metric box with the room beyond it (a far background: photos circling their
    subject), whether the losses that warp pixels between training views act: L_geo (Eq. 10, both summands) and the
    photometric terms. "auto" (``objective.warp_regime``): off where most of the points the training views
    triangulate lie beyond the box (what the photos share is the room, whose depth in the box L_geo cannot match;
    the juice box's wide split 13.49 -> 15.42 dB over 2 seeds, its own photos 17.7 -> 22.7 dB), on where the content stands in
    the box (the bird, which loses 6.7 dB without them): docs/notes/captures.md, "Two regimes". LLFF in NDC, DTU
    and Blender have no room: the warps always act there, as in the paper. The start-up summary says which."""
