"""Imaging room: read case folders, align, segment, warp, contour mismatch, digital image correlation."""
