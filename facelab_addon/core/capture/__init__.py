"""What a capture gives FaceLab: pinhole cameras, markers bound to the surface, point-cache files
(PC2/MDD) and the ICT-FaceKit reader (the project's test and demo face)."""
