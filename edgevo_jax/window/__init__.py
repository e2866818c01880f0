"""The sliding window (the local map of the paper): keyframes refined jointly (poses, inverse
depths, intrinsics; ``sliding``, ``problem``, ``refine``), the Schur complement
(``schur``) and marginalisation into a prior (``prior``), edge activation (``activation``)
and the worker that runs it beside tracking (``worker``)."""
