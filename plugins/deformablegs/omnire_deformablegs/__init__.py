"""DeformableGS baseline plugin for omnire (node type ``deformable_field``, method ``deformablegs``)."""
