// A slender bar of configs/slender_beam.yaml, drawn in millimetres (the config's scale: 0.001
// makes metres): 2000 mm long along x, 10 mm x 10 mm square section. Physical groups name the
// end faces root (x = 0) and tip (x = L) and the volume body.
SetFactory("OpenCASCADE");
L = 2000;  a = 10;  eps = 1e-3;
Box(1) = {0, 0, 0, L, a, a};
Physical Surface("root") = Surface In BoundingBox {-eps, -eps, -eps, eps, a + eps, a + eps};
Physical Surface("tip") = Surface In BoundingBox {L - eps, -eps, -eps, L + eps, a + eps, a + eps};
Physical Volume("body") = {1};
