"""Parameters of the TrackDeform3D pipeline: one frozen dataclass, SI units (metres, pixels, frames)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TrackingParams:
    """All knobs of segmentation, initialisation, solver and tracking (defaults suit a 1 m camera distance).

    Segmentation
      depth_min_m, depth_max_m: valid depth range, m; readings outside are ignored.
      diff_abs_m: minimum depth change that counts as a change, m.
      diff_noise_coeff: depth noise model sigma(z) = coeff * z**2 (1/m); threshold = max(abs, k * sigma).
      diff_sigma_k: how many sigmas of noise a change must exceed.
      arm_margin_px: dilation of the rendered arm silhouette, px (at full resolution).
      arm_margin_m: a pixel is arm if its measured depth is farther than rendered arm depth minus this, m.
      arm_render_stride: rays are cast every this many pixels (then upsampled), px.
      lift_stride: foreground pixels are lifted every this many rows and columns, px.
      decimate_pixel_m: LivePipeline first decimates each depth image by s = round(fx * this) (a
        pixel then spans about this at 1 m, so any resolution gives the same cloud) and segments
        the decimated image with lift_stride 1 (0: no decimation, lift_stride applies), m.
      voxel_m: voxel size of the down-sampled object cloud, m (3-5 mm).
      dbscan_eps_m, dbscan_min_points: DBSCAN neighbourhood radius (m) and core size.
      dbscan_voxel_m: DBSCAN runs on the cloud voxelised this coarsely (labels spread back), m.
      min_cluster_points: clusters smaller than this (voxels) are noise.
      cluster_keep_fraction, cluster_keep_gap_m: at initialisation also keep clusters at least this
        fraction of the largest and within this gap of it (an object split by a gripper), m.
      grow_step_m: the initial (difference) segmentation grows over changed pixels reachable from
        the object through depth steps of at most this between neighbouring pixels (0: no growth), m.
      attach_reach_m, attach_step_m, attach_max_spread_m: a 1D object's difference cloud is completed
        with the pixels within this reach of it, m, that belong to it though they did not move: those
        standing at least attach_min_height_m (m) above the table (the reference's dominant plane:
        attach_plane_min_fraction of its pixels within attach_plane_tol_m, m, or, where the depth noise
        is wider, within support_sigma_k times it: a far table; the height, too, is at least that many
        times the depth noise where it is wider than attach_min_height_m; without a plane, no
        height test) and reachable through depth steps of at most attach_step_m between
        neighbouring pixels, m; each added part must be thin (lateral spread at most
        attach_max_spread_m, m). attach_step_px: the step is at least this many pixel footprints (a
        tube at up to ~79 degrees to the image plane on a decimated image, e.g. a branch hanging away from
        a camera above). An end dragged along the
        table (reach 0: off). attach_iterations:
        how many times the growth may repeat while a holding gripper's TCP is not reached.
      track_attach_iterations: in tracking, a 1D object's segmentation is grown so too, up to this many times
        a frame (``complete_thin_parts``; 0: off): a part where the object stood in the references is its own
        background there and is regained only by its continuity with what is seen.
      no_return_open_m: a region of the references without a reading in any of them and wider than
        this at 1 m is empty space beyond the sensor's range: its background is depth_max_m, so an
        object in front of it counts as changed (0: such pixels stay unknown), m.
      track_gate_m: in tracking, a cluster is kept if some point lies within this of the previous keypoints, m;
        of a 1D object's kept clusters only the points within this of the previous object.
      track_attach_m: in tracking, points DBSCAN leaves out are kept within this of the parts of the
        previous object the kept clusters do not cover, and a cloth's points of kept clusters less than
        attach_min_height_m above the table only within this of the previous object (``select_clusters_near``), m.
      tip_reach_m, tip_step_m, tip_cone_cos: a 1D object's free tip (a leaf no gripper holds) takes the points
        DBSCAN left out within tip_reach_m (m) of it and within the cone of that cosine around the direction its
        last edge points, chained to it in steps of at most tip_step_m (m): a branch hanging towards or away from
        the camera lifts to a few points a decimated pixel or two wide, too sparse for DBSCAN and beyond
        track_attach_m of the previous object, and its keypoints bunched at the end of what was kept (0: off).
      held_chain: a cloth's held corners take the points DBSCAN left out chained to them in steps of at most
        tip_step_m (m), any direction, within the sheet's reach over its rest lengths (``tracker.held_seeds``): a
        side turned edge-on below the hand lifts to points several centimetres apart in depth, and once the grid
        has left it nothing near the previous object keeps them.
      colour_band_m, colour_min_separation, colour_radius_m: with the frame's colour, a 1D object's left-out points
        less than colour_band_m (m) above the table (the height the table's stereo noise reaches beside a part
        lying on it) stay out where their colour is the table's (``tracking.colour``): the object's where a pixel
        within colour_radius_m (m, at the point's depth) of the point's own is, the table's where their own pixel
        is nearer the reference frame's chromaticity there; told only where that lies farther than
        colour_min_separation (or three robust deviations of the object's own) from the object's.
      background_object_gap_m: a farther reading is absorbed into the background only if its 3D
        point lies more than this from the tracked object (last cloud, keypoint edges): else it is
        the object moving away from the camera, m.
      background_confirm_1d, background_confirm_2d, background_jump_k: a farther reading replaces the
        background when it is more than background_jump_k change thresholds behind in this frame and
        behind in the previous one (a revealed surface), or else when this many consecutive frames
        (the current one included) are all behind it, taking the nearest of them (noise ratchets the
        background farther otherwise). A rope lying on the table stands only 1-2 change thresholds in
        front of it, the band the ratchet fills with speckle: 1D objects wait 3 frames and take the
        nearest reading; a cloth resting on the table is within the noise of it anyway: 2D objects
        wait 2 and take the current reading.
    Classification
      classify_seeds, classify_radius_m, classify_k: number of random seeds, neighbourhood radius (m)
        and maximum neighbours per seed.
      line_ratio_max: median lambda2/lambda1 below this means 1D.
      plane_ratio_max: median lambda3/lambda2 below this (and not 1D) means 2D.
    Image-space anchor detection
      mask_pixel_m: target pixel footprint of the object mask, m (the image is scaled down to it).
      junction_merge_m: junction pixels closer than this are one junction, m.
      spur_length_m: leaf branches shorter than this are pruned, m.
      lift_radius_px, lift_k: skeleton pixels are lifted as the median of up to k cloud points
        projected within this radius, px (mask pixels).
      end_extend_m: leaf anchors are pushed along the branch tangent to the cloud's tip within this, m.
      end_axis_m: a leaf is first put on the axis of its branch, a line fitted over this much of it, m.
      end_slab_m: a pushed leaf is centred on the cloud points within this of the tip along the branch, m.
    1D initialisation
      n_keypoints_1d: total keypoints of a 1D object (anchors included).
    2D initialisation
      grid_rows, grid_cols: cloth keypoint grid.
    Solver (Algorithm 1)
      init_iterations, track_iterations: Gauss-Seidel sweeps at initialisation / per tracked frame.
      use_anchors, use_edge_projection, use_cloud_projection: ablation switches.
      surface_k: cloud projection = nearest point when <= 1 (the paper), else nearest point plus the
        tangential offset on the local PCA plane of this many neighbours (no snapping to voxel centres).
      surface_slide_m: largest tangential offset from the nearest point, m.
      ridge_radius_m: a 1D object's free initial keypoints are finally moved to the ridge of the
        tube's visible skin, found from the cloud within this radius (0: off), m.
    Tracking (Algorithm 2)
      anchor_gate_m: Hungarian matches of re-detected to predicted anchors farther than this are rejected, m.
      anchor_regate_m: leftover anchors and detections are matched again within this wider gate, m: a cloth's
        anchor only if it was not re-detected and kept the frame before (``Tracker.step``); a 1D one kept the frame
        before only by a detection off the rest of the object (``anchor_regate_clear``): a tip whipping in fast
        motion outruns its constant-velocity prediction, a spur of the skeleton lies on the object.
      anchor_regate_clear: that detection's least distance to the other predicted keypoints (not the anchor's
        neighbours), in median rest lengths.
      anchor_edge_tol: two re-detected anchors joined by an edge whose length differs from its rest
        length by more than this fraction of it are both left free this frame (0: off).
      anchor_neighbour_slack_m: so is a re-detected anchor whose distance to the predicted position
        of a neighbour that is not one differs from their edge's rest length by more than
        anchor_edge_tol of it plus this, m (a rope's free end matched to a spur a few cm off).
      anchor_stiffness: in (0, 1]: how far a re-detected junction (1D) or boundary anchor (cloth) pulls its
        keypoint after each solver iteration (1: fixed there, the paper's hard constraint): their detections
        carry the depth noise and contour error that a fixed anchor passes on to its edges. A 1D object's
        tips and grasped keypoints are fixed, except a tip seen short (``tip_short_tol``).
      grow_frames: a free 1D tip re-detected beyond its chain's reach ((1 + grow_tol) of the chain's rest length
        from its other node) in this many frames running lengthens the chain to that reach (0: never).
      grow_tol: that margin, a fraction of the chain's rest length.
      grow_retrack_frames: offline, a chain lengthened within this many frames of initialisation has those
        frames, and the ones before initialisation, tracked backwards from the frame after it with the
        lengthened chain (kept where better: fewer tangles, smaller edge error; 0: never).
      tip_short_tol: a re-detected 1D tip nearer its one neighbour's predicted position than its edge's rest
        length by more than this fraction of it (the tip end-on, bent away or partly hidden, so the cloud's
        extreme point lies inside the object) pulls its keypoint like a junction instead of fixing it, when
        it is within anchor_gate_m of the tip's prediction (0: every tip fixed).
      relift_span_tol: a cloth grid folded over itself is re-lifted from the frame's contour only when the
        fresh grid's edges add up to the rest lengths within this fraction (the contour outlines the whole
        cloth and nothing else; measured: 0.95-1.03 on twisted test-bed cloths, 0.84-0.93 over a fold in the
        project's simulator, whose hidden lower layer the contour cannot show, up to 1.23 as it closes).
      cover_gap, cover_trigger: a grid is registered again to its frame's cloud (``tangle.cover_cloud``) when more
        than cover_trigger of the cloud lies farther than cover_gap median rest lengths from the grid's surface (the
        grid folded onto part of the sheet it sees, the rest of the sheet uncovered; below 0.05 on a right grid).
      cover_gain, cover_abs_slack_mm: such a registration is kept when it leaves less than cover_gain of the share
        uncovered before, fewer tangled cells (none where there were none) and an edge error (RMS, mm) at most
        cover_abs_slack_mm above the solve's.
      cover_iterations, cover_points, cover_pull_gap, cover_step, cover_keypoint_step, cover_sweeps: the
        registration's iterations; the cloud points it samples; how far (median rest lengths) a cloud point may be
        from the grid's surface before it pulls the surface's nearest point towards it, and the fraction of the way
        it does; the fraction of the way each keypoint goes to its nearest cloud point (all of it from where the
        camera sees through it); the edge sweeps after each iteration.
      fold_cos: a 1D keypoint chain has folded onto itself where the cosine between a keypoint's edge in and
        edge out is below this (turned back by more than 120 degrees over one keypoint spacing; the test
        bed's true centrelines sampled at the keypoint spacing stay above +0.5 in every rope clip).
      fold_span_min: a folded chain is laid out again along itself only when its polyline without the fold
        spans at least this fraction of the chain's rest length (else the object's missing part is out of
        sight, e.g. a branch hanging towards the camera, and spacing the chain on what is seen compresses it).
      fold_capture: a turned-back keypoint within this fraction of the median rest length of a keypoint of
        another chain (one it is not on) has been captured by that part of the object: its chain is laid out
        again whatever its span, and the solution from there is kept, if it has fewer folds, with an edge error
        up to fold_capture_abs_mm (mm) even where the captured one's was lower (the captured keypoint fits its
        edges along the other part better than the chain's true, partly hidden, shape does).
      grasp_gate_m: a TCP farther than this from every keypoint holds nothing, m (a hand hides the few
        centimetres of a held rope between its fingers: the end seen nearest to a TCP lies up to ~7 cm from it).
      hidden_reach: a keypoint out of sight (``tracking.geometry.hidden_behind``: a 1D one behind the arm, a
        cloth's behind whatever the depth shows in front of it, the arm or the cloth's own near layer) is
        projected onto the cloud only when its nearest point lies within this fraction of the median edge rest
        length (the rope just beside the fingers); farther, the cloud it would be pulled onto is another part of
        the object (a cloth turned edge-on: its near strip), and the edges, its grasp and its hand's motion
        place it instead. A cloth keypoint in open space with such a layer within this reach across the image
        is out of sight behind it too (``hidden_behind``'s reach_m), not pulled onto the layer's nearest point.
        A 1D keypoint whose nearest cloud point lies beyond this reach and nearer another keypoint, not its
        neighbour, is solved as a hidden one (``tracker.cloudless``: its own part is out of sight where no arm
        mask says so, e.g. under a hand seen from above, and that cloud is another part of the object).
      hidden_bend: each solver sweep, such a hidden 1D keypoint moves this fraction of the way to where its chain
        runs smoothest (least second differences over two neighbours each side): the hidden stretch continues the
        seen rope's direction into the hand instead of cutting a straight chord; more fights the edge lengths.
      hidden_stretch: nor is such a hidden keypoint projected onto a point farther from a fixed neighbour (the
        held end next to it) than its edge's rest length times 1 + this: the hand hides more rope than one edge.
      hidden_relax_sweeps: after a cloth's frame is solved, this many sweeps of its edge projections move only
        its hidden keypoints (the seen and the held ones fixed): a part of the sheet out of sight keeps its edge
        lengths instead of staying pressed onto the seen surface beside it, where the frame's cloud projections
        left it (a twisted cloth's far half behind its edge-on strip: edges off by 10-30 mm). 0: off.
      exit_keypoints, exit_stiffness: a 1D keypoint within exit_keypoints edges of a held one and hidden behind
        the arm is pulled exit_stiffness of the way (a soft anchor) to where it was last seen in that gripper's
        frame: the fingers clamp the rope, so it leaves them the way it did, in an arc the smoothest curve through
        the hidden stretch (``hidden_bend``) does not follow. Needs the TCP orientations (``Tracker.step``).
      exit_keypoints_2d: the same for a cloth, whose held corner the fingers clamp too: its grid neighbours one
        edge away (two edges take in the cell's far corner, which the cloth's drape moves: measured worse).
      hand_hidden_m: a 1D object's initial growth towards a gripper that stops short of its TCP is kept when
        it stops within this of the TCP and the rest of the way is hidden behind the arm in the image (a hand,
        whose fingers and body span about this much around its TCP, hides the end it holds), m.
      causal_window, symmetric_window: moving-average windows, frames.
      smooth_gate: the symmetric average leaves out a pair of frames whose midpoint is farther than this many
        median rest lengths from the frame it smooths (a jump: ``tracker.smooth_symmetric``).
      smooth_edge_slack_mm: a grid's frame whose smoothed edges are off their rest lengths by more than this (RMS,
        mm) beyond its raw ones keeps its raw keypoints: the mean of two frames across a fold or a re-lifted grid is
        not a shape the cloth took (``tracker.final_keypoints``).
      tube_mean_half, tube_mean_reach: a tracked 1D keypoint in sight (neither hidden nor held nor a junction) is
        reported at the mean of the cloud in its slice of the tube, within tube_mean_half median rest lengths of it
        along its chain and tube_mean_reach across, moved across the chain only (``solver.tube_mean``); each chain
        is then spaced along its reported curve as its rest lengths are (``tangle.respace_chains``, moves of at
        most respace_cap). The solve's keypoints stay the next frame's warm start. The solve leaves a keypoint on
        one point of the cloud, with that point's depth noise (~2 mm RMS at 1 m, 4-6 mm at 1.5-1.9 m on the test
        bed's stereo), wherever across the tube its edges pulled it. tube_mean_half 0: off.
      stretch_abs_mm, stretch_sweeps: a cloth's keypoints whose edge error is above stretch_abs_mm (mm) are
        reported with their edges longer than their rest lengths shortened (stretch_sweeps Jacobi sweeps,
        ``solver.shorten_stretched``, held ones fixed) and those in sight put back onto the plane of their nearest
        cloud points (``solver.onto_local_plane``), when that lowers the edge error: the cloth does not stretch,
        and the cloud projection that ends each solve iteration leaves edges stretched across a fold or a twist.
        A shorter edge is left alone (a fold the 6x6 grid cannot show). stretch_sweeps 0: off.
      respace_cap, respace_error: in a frame where the RMS of a chain's edge length errors exceeds respace_error
        median rest lengths, a 1D object's final keypoints are spaced along that chain's tracked curve in
        proportion to their rest lengths (``tangle.respace_chains``: a rope does not stretch, and the solve can
        leave one edge long and another short where the cloud pulls keypoints along the rope, or beside a hand
        that hides the rope), each moving at most respace_cap median rest lengths (a curve that detours across a
        gap is not followed far). respace_cap 0: off.
      min_object_points: fewer segmented points than this is a bad frame.
      max_edge_rmse_m, max_chamfer_m: a frame with Abs or CD above these is bad, m.
      max_jump_m: a frame whose median keypoint displacement from the previous frame exceeds this
        is bad and its solution is discarded, m.
      lost_after_frames: this many consecutive bad frames means the track is lost.
    seed: random seed of every sampled step.
    """

    depth_min_m: float = 0.15
    depth_max_m: float = 4.0
    diff_abs_m: float = 0.004
    diff_noise_coeff: float = 0.0012
    diff_sigma_k: float = 3.0
    arm_margin_px: int = 6
    arm_margin_m: float = 0.02
    arm_render_stride: int = 2
    lift_stride: int = 2
    decimate_pixel_m: float = 0.0045
    voxel_m: float = 0.004
    dbscan_eps_m: float = 0.015
    dbscan_min_points: int = 3
    dbscan_voxel_m: float = 0.009
    min_cluster_points: int = 10
    cluster_keep_fraction: float = 0.05
    cluster_keep_gap_m: float = 0.08
    grow_step_m: float = 0.02
    attach_reach_m: float = 0.03
    attach_iterations: int = 40
    attach_max_spread_m: float = 0.008
    attach_step_m: float = 0.01
    attach_step_px: float = 5.0
    attach_plane_tol_m: float = 0.004
    attach_plane_min_fraction: float = 0.3
    support_sigma_k: float = 2.0
    attach_min_height_m: float = 0.005
    track_attach_iterations: int = 10
    no_return_open_m: float = 0.02
    track_gate_m: float = 0.05
    track_attach_m: float = 0.025
    tip_reach_m: float = 0.06
    tip_step_m: float = 0.03
    tip_cone_cos: float = 0.9
    held_chain: bool = True
    colour_band_m: float = 0.01
    colour_min_separation: float = 0.05
    colour_radius_m: float = 0.008
    background_object_gap_m: float = 0.015
    background_confirm_1d: int = 3
    background_confirm_2d: int = 2
    background_jump_k: float = 2.0

    classify_seeds: int = 64
    classify_radius_m: float = 0.03
    classify_k: int = 64
    line_ratio_max: float = 0.25
    plane_ratio_max: float = 0.3

    mask_pixel_m: float = 0.002
    junction_merge_m: float = 0.02
    spur_length_m: float = 0.03
    lift_radius_px: float = 3.0
    lift_k: int = 8
    end_extend_m: float = 0.03
    end_axis_m: float = 0.025
    end_slab_m: float = 0.01

    n_keypoints_1d: int = 25
    grid_rows: int = 6
    grid_cols: int = 6

    init_iterations: int = 100
    track_iterations: int = 30
    use_anchors: bool = True
    use_edge_projection: bool = True
    use_cloud_projection: bool = True
    surface_k: int = 8
    surface_slide_m: float = 0.003
    ridge_radius_m: float = 0.012

    anchor_gate_m: float = 0.05
    anchor_regate_m: float = 0.15
    anchor_regate_clear: float = 0.5
    anchor_edge_tol: float = 0.15
    anchor_neighbour_slack_m: float = 0.02
    anchor_stiffness: float = 0.2
    tip_short_tol: float = 0.15
    grow_frames: int = 3
    grow_tol: float = 0.05
    grow_retrack_frames: int = 30
    relift_span_tol: float = 0.06
    cover_gap: float = 0.35
    cover_trigger: float = 0.1
    cover_gain: float = 0.5
    cover_abs_slack_mm: float = 1.0
    cover_iterations: int = 30
    cover_points: int = 800
    cover_pull_gap: float = 0.15
    cover_step: float = 0.7
    cover_keypoint_step: float = 0.3
    cover_sweeps: int = 8
    fold_cos: float = -0.5
    fold_span_min: float = 0.8
    fold_capture: float = 0.5
    fold_capture_abs_mm: float = 3.0
    grasp_gate_m: float = 0.08
    hidden_reach: float = 0.5
    hidden_bend: float = 0.1
    hidden_stretch: float = 0.1
    hidden_relax_sweeps: int = 10
    exit_keypoints: int = 2
    exit_keypoints_2d: int = 1
    exit_stiffness: float = 0.2
    hand_hidden_m: float = 0.12
    causal_window: int = 3
    symmetric_window: int = 5
    smooth_gate: float = 2.0
    smooth_edge_slack_mm: float = 1.0
    tube_mean_half: float = 0.25
    tube_mean_reach: float = 0.5
    stretch_abs_mm: float = 4.0
    stretch_sweeps: int = 5
    respace_cap: float = 0.5
    respace_error: float = 0.1
    min_object_points: int = 30
    max_edge_rmse_m: float = 0.015
    max_chamfer_m: float = 0.015
    max_jump_m: float = 0.08
    lost_after_frames: int = 5

    seed: int = 0
