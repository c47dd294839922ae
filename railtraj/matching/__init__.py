"""Algorithms shared by the local matching stages (detectors, descriptors, matchers).

voxel       voxel grids that keep raw-point membership (keypoint times, block plane fits)
neighbours  radius neighbourhoods and closed-form 3x3 eigen problems, vectorized
keypoints   detector output -> Keypoints (top N, gps_time of a real point)
voting      translation votes of keypoint pairs, peaks, histogram slices
target      the reference surface: local planes on a 5 cm grid
refine      point-to-plane Gauss-Newton, noise-corrected information, covariance
consensus   dense check of candidate offsets, alias test, consensus ties
resolve     the end every voting matcher shares: peaks -> check -> refine -> TileOffset
synthetic   small seeded tunnel clouds for tests and benchmarks
"""
