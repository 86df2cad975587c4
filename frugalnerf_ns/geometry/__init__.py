"""Floor 1, geometry: pure-torch rays and cameras, tested without nerfstudio's models.

NDC warps (``ndc``), ray-box intersection and sample positions (``raymarch``), reprojection and depth
warps between views (``reprojection``), camera-convention changes and the one look-at frame
(``camera_conventions``), the poses of novel views and videos (``novel_views``, ``video_path``), what the
cameras say about a scene: forward-facing or surrounding, its box, the grid a pixel count asks for
(``scene_analysis``), and the epipolar geometry of two views: the fundamental matrix of two projections and
each match's distance from its epipolar line, a check of converted cameras (``epipolar``); dense two-view stereo
by plane sweep (``plane_sweep``), the space beyond a scene box as a bounded volume (``contraction``), which
cameras see a set of points (``visibility``) and where a next photo could be taken (``viewpoints``). Imports only
the package root (errors, progress) and other floor-1 rooms.
"""
