"""Exports of the building models: OBJ (groups per building and surface type), CityGML 2.0 LoD2, CityJSON 2.0."""
