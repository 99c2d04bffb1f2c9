"""Star identification: the Tetra pattern database (``database``), lost in space (``lost_in_space``), tracking from
a prior attitude (``tracking``) and the geometry they share (``geometry``)."""
