"""Spatial refinement of local edits (paper §3.3, SPEC §3): 3D cross-attention grids, graph cut, merge.

One module per step: :mod:`~voxe_core.refine.config` (``RefineConfig``), :mod:`~voxe_core.refine.maps`
(2D attention maps), :mod:`~voxe_core.refine.lifting` (the 3D attention grids), :mod:`~voxe_core.refine.cut`
(probabilities and the graph cut), :mod:`~voxe_core.refine.pipeline` (merge and :func:`~voxe_core.refine.pipeline.refine`,
the whole of it), :mod:`~voxe_core.refine.storage` (mask and probability files) and
:mod:`~voxe_core.refine.renders` (pictures of fields and masks).

Pipeline (``refine``):

1. :func:`attention_maps_2d` renders views of the edited grid G_e from random
   upper-hemisphere poses and asks the diffusion model for per-token
   cross-attention maps (one UNet pass at t = 200), the prompt carrying each
   pose's view word (", front view", as in the edit). The *edit* map is the
   max over the edit words' tokens (every sub-token of every occurrence), the
   *object* map the element-wise max over every other token of the prompt and
   the first end-of-text token (start and padding tokens excluded). Each map is
   smoothed with a 3×3 Gaussian (σ = 0.5 cells) on the attention lattice (on
   whatever device it lives), upsampled bilinearly to the render size, smoothed
   again and min-max normalised per view. All of this but the last step is the
   authors' code's (``AUTHORS_CODE_MAPS`` keeps raw probabilities, so the two
   maps keep their relative scale); min-max maps cut better on the mesh scenes
   of bench/localisation_maps_fit.py and on the fox of bench/localisation_grids.py
   (``SERVICE_MAPS``, the default). ``PAPER_TEXT_MAPS`` gives the mean over edit
   tokens, no view word, content tokens only, one σ = 1 blur and min-max maps.
2. :func:`fit_attention_grids` lifts both sets of maps into two scalar grids
   sharing G_e's frozen density. A field's value is rendered **raw** (no
   activation), as a grey value composited over a black background, and fitted
   by L1 to the maps plus ``tv_weight`` · TV, with Adam; the L1 counts only the
   pixels whose rendered attention is > 0 (``fit_pixels``, the code's), and
   every step sees a new pose and diffusion pass (``fit_views="fresh"``, the
   code's; ``"fixed"``: pixels of the start's views, no UNet pass). The render is linear
   in the field over the frozen density, so the fit starts from the weighted
   back-projection of the maps (``lift_start="backprojection"``, every
   ``backprojection_stride``-th pixel row and column) and Adam moves only the
   vertices those pixels see (with a constant start too; a fresh view moves no
   other, and a back-projection that sees none is refused); on
   bench/localisation.py the back-projection alone (``iterations=0``) cuts as
   well as the paper's 1,500-step fit from a constant (``lift_start="constant"``).

   Initial value: the authors initialise the feature to −20. Rendered raw, an
   untrained −20 grid renders −20·opacity, far outside the [0, 1] range of the
   targets: Adam at lr 0.035 moves a value about lr per step, so ~570 of the
   1500 steps would be spent climbing back into range. Rendered through a
   sigmoid the −20 start is black but its gradient is sigmoid'(−20) ≈ 2e-9,
   below Adam's epsilon, so it barely moves at all. We therefore render the raw
   value (the fit is then convex: a linear render under an L1 loss) and
   initialise at 0, which *is* the background value: an untrained field renders
   exactly "no attention", and voxels no view ever sees keep 0 in both grids,
   i.e. probability 1/2 each (no evidence either way; the graph cut's
   smoothness term labels them from their neighbours). ``init_value=-20``
   reproduces the authors' start.
3. Per voxel, P_e, P_obj = softmax(edit value, object value), computed in
   log space (finite for any finite logits, e.g. ±1e4).
4. :func:`graph_cut` labels the occupied voxels of G_e (by default, as the authors'
   code: vertices whose 3×3×3 max-pooled ReLU density is > 0; ``node_rule="alpha"``:
   those whose activated density makes a voxel-length at least ``node_alpha`` opaque) by
   Boykov–Kolmogorov max-flow (PyMaxflow), built vectorised. The default cut
   (``SERVICE_CUT``, the authors' code's but for two choices) ties its seeds
   to their terminal with a capacity larger than any finite cut (edit seeds:
   the nodes within ``edit_seed_ratio`` of the largest P_e; object seeds:
   drawn at random among P_obj > P_e + ``object_seed_margin``), gives the
   unseeded voxels no unary cost, and weighs 6-neighbour pairs along all
   three axes by
   λ·exp(−‖c_p − c_q‖ / σ) on G_e's activated colours; a piece of the graph no
   seed reaches takes the label its voxels' probabilities favour.
   ``PAPER_TEXT_CUT`` gives the paper's text instead: unary costs −log P of the
   label at every voxel, the top-P seeds, Gaussian weights
   λ·exp(−‖c_p − c_q‖² / 2σ²) and the ``node_alpha`` nodes.
5. :func:`merge`: G_r = M·G_e + (1 − M)·G_i voxel-wise on all four features;
   unmasked voxels are bit-identical to G_i.

Storage: :func:`save_mask` keeps only the flat indices (int32) of the set
voxels plus the grid shape; :func:`save_probabilities` keeps the probability
grids at the occupied voxels only (indices + values). Both are versioned
safetensors files (no pickle).
"""

