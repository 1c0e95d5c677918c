"""The stages of worldbake: one subpackage per stage, each exporting STAGE."""
