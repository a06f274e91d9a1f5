"""Motion generation (gait, swing, trunk references) and the sWBC / c3WBC whole-body QP controllers; node wbc."""
