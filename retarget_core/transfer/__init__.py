"""Contact transfer from a source hand to a target hand (paper: "Contact Alignment")."""
