"""Contact and joint friction (paper §5, Alg. 2-3; docs/friction.md): the compiled friction model, contact
detection and the stacked rows (contact.py), condensation of the bilateral rows (condense.py), BISP's affine
joint-wrench map of Eq. (15)-(17) (bisp.py), and the Staggered Projections / BISP iterations (staggered.py)."""
