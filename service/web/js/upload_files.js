// What each dropped file is for the upload form: photos, match files, a calibration file or a zip. Pure.

const MATCH_FILE = /^matching\d+\.txt$/i;
const IMAGE_FILE = /\.(png|jpe?g|mp4|mov|m4v|mkv|webm|avi)$/i;  // photos, or one video of the object

// "matches" | "calibration" | "zip" | "images", or null for a file the service would not take.
export function fileRole(name) {
  if (MATCH_FILE.test(name)) return "matches";
  if (/\.txt$/i.test(name)) return "calibration";
  if (/\.zip$/i.test(name)) return "zip";
  if (IMAGE_FILE.test(name)) return "images";
  return null;
}

export const emptyChoice = () => ({ images: [], matches: [], calibration: null, zip: null });

// Adds files ({name}) to a choice; returns the names left out. A later calibration or zip replaces the earlier.
export function addToChoice(chosen, files) {
  const leftOut = [];
  for (const file of files) {
    const role = fileRole(file.name);
    if (role === "images" || role === "matches") chosen[role].push(file);
    else if (role) chosen[role] = file;
    else leftOut.push(file.name);
  }
  return leftOut;
}

export const choiceSummary = (chosen) =>
  `${chosen.images.length} photo(s)${chosen.zip ? ` and ${chosen.zip.name}` : ""}, `
  + `${chosen.matches.length} match file(s), calibration: ${chosen.calibration ? chosen.calibration.name : "none"}`;
