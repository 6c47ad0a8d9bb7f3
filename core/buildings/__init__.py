"""LOD2 buildings with discontinuities, roof overhangs and dormers from the oblique point cloud and the DSM.

Pipeline per building (:func:`.reconstruct.reconstruct_building`):

1. :mod:`.detect`: buildings from the nDSM and masks (or user footprints), one point set each, ground from the DTM.
2. :mod:`.denoise`: voxel noise filter (PCA plane per voxel from its 3x3x3 neighbourhood, sphere r = a/2 sqrt 3,
   distance histogram, points beyond the modal class removed).
3. :mod:`.contour`: facade cells, RANSAC line per cell, 8-neighbourhood merging, regression lines, closed contour
   (roof-outline fallback when there are no facade points).
4. :mod:`.roof`: cell planes, smoothness, normal groups, region growing, 2x2-window topology (edges, nodes), arrises
   along the contour, group planes, edges and nodes from plane intersections, and the agreement check.
5. :mod:`.dormers`: blocks of points above a sloped roof plane, modelled as gabled or shed dormers (2D path).
   :mod:`.hull`: the closed body from the plane arrangement (2D path: contour walls + roof planes + ground + the
   dormers' planes, occupancy from the label grid joined with the dormers'); :mod:`.volumetric`: the fallback's
   planes when the check fails, or when the 2D model misses its roof points and the fallback fits them clearly
   better (``ReconstructionConfig.misfit_2d``): region growing over voxels with their 3x3x3 blocks' planes, faces
   rising from the outline's edges by a vote, occupancy from the top surface snapped to those planes.
6. :mod:`.overhang`: eave offsets on the DSM (zero crossing of the second directional derivative, placed by a
   two-line step fit, less the DSM's half-cell outward shift), overhang slabs.
7. :mod:`.model`: the building model and ``buildings/buildings.json``; :mod:`.stage`: the ``buildings`` stage.
"""
