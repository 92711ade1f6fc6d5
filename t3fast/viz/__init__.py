"""Pictures of occupancy: bird's-eye PNG/GIF (:mod:`t3fast.viz.bev`), self-contained 3D pages
(:mod:`t3fast.viz.viewer`, labels packed by :mod:`t3fast.viz.voxel_pack`) and the demo's
``index.html`` (:mod:`t3fast.viz.index_page`)."""
