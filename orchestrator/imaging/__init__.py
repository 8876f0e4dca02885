"""Imaging: what the two images show before any mechanics. Segmentation of a T1 slice (`segment`), the rigid
alignment on the bones in 2D and 3D (`align`, `align3d`), the fat's chemical shift (`chemical_shift`), muscle
compartments at the septa (`compartments`), the texture coherence of the slices (`coherence`), contour mismatch
(`mismatch`), warping (`warp`) and checks of a displacement field (`field_checks`).

Positions are in mm in the frame of the unloaded image I0 (x right along columns, y down along rows, pixel (i, j)
centred at ((j + 0.5) dx, (i + 0.5) dy)); pixel_size_mm = (dy, dx); displacement fields are (2, H, W) arrays in mm.
"""
