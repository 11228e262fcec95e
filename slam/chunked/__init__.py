"""One long sequence across several workers (``slam run SEQ --workers N``): the frame list is
cut into chunks that overlap (:mod:`~slam.chunked.plan`), each chunk runs the ordinary
:class:`~slam.system.Slam` in its own worker process (:mod:`~slam.chunked.worker`, on Ray or
local processes: :mod:`~slam.chunked.executor`), and the join (:mod:`~slam.chunked.join`)
chains the chunks through their overlapping frames and replays their keyframes through one
loop closer, so loops between chunks close, the pose graph and bundle adjustment span the whole
run, and every submap is re-fused under its corrected anchor (:mod:`~slam.chunked.runner`)."""
