"""The 3D Gaussian Splatting map: parameters, renderers (CPU and CUDA), growth, optimisation,
keyframes and the standard PLY layout."""
