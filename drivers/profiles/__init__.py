"""Device profiles (CiA 4xx) the master speaks; :mod:`drivers.profiles.p402` is the drive profile."""
