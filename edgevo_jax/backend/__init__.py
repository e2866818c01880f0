"""The local map (the back end): a sliding window of keyframes refined jointly (poses,
inverse depths, intrinsics), the Schur complement and marginalisation, edge activation."""
