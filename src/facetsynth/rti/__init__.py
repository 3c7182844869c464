"""Light-dome (RTI) captures: reflectance transformation imaging, where a fixed
camera looks at the sample under many known light directions (a dome or a
hand-held light), and the per-pixel relighting fits (:mod:`.fits`: Lambert,
PTM, HSH) that RTI users compare against."""
